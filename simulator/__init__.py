"""Synthetic scene, renderer with ground truth, virtual sensors and hardware emulators."""
