"""Rendering a recorded take with a model, outside the live loop: `rig model render`'s views and
orbit video of a take (take.py), and novel views in place of a take's supervision cameras beside
what those cameras recorded (novel_views.py, the demo's last step).

The model runs as in `rig live`: the exported model in ONNX Runtime, or with a CUDA device the torch
GPU runtime; the viewpoints are the live page's (`rig.live.viewpoint`).
"""
