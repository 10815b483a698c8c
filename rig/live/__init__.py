"""Live free-viewpoint output: FrameSets through the ONNX Runtime pipeline to web viewers."""
