"""Splat-SAP: networks (torch), training, ONNX export, and the torch-free ONNX Runtime pipeline."""
