"""Measuring the pipeline: geometry checks against the simulator's ground truth."""
