"""Calibration from board images on disk: the rig's cameras in one frame (`run.py`, for `rig
calibrate run`) and each camera's lens from its own session (`intrinsics.py`, for `rig calibrate
intrinsics`). Both check every input first, then detect the board in every image and solve; the
views themselves come from `rig calibrate capture` (rig/capture/calibration_views.py) or any camera.
"""
