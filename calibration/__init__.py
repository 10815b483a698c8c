"""Camera models, boards, detection, solving, reports and exports for the rig's calibration."""
from calibration.camera import CalibrationError, CameraModel, RigCalibration, look_at

__all__ = ["CalibrationError", "CameraModel", "RigCalibration", "look_at"]
