"""The Splat-SAP networks in torch: backbones, the stage-1 affine transform, depth initialisation,
stage 2 (depth refinement, colour blending, Gaussian plane), the plane splatter, and checkpoints.
`pipeline.SplatSAP` joins them into the whole model."""
