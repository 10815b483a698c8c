"""Training of Splat-SAP: losses (and, as it grows, data, trainer)."""
