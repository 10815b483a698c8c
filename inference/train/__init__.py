"""Training of Splat-SAP: losses, differentiable point splatting, Chamfer, data, stages and the trainer."""
