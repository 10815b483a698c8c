"""What `rig calibrate run` and `rig calibrate intrinsics` share: the lens terms to fit or hold, and
the board's detection in every image."""
from __future__ import annotations

from dataclasses import dataclass

# The --k3 and --tangential choices as the solver's options: auto decides from the views' number.
_HOLD = {"auto": None, "hold": True, "fit": False}


@dataclass(frozen=True)
class LensChoices:
    """`outlier_px`: views whose RMS exceeds max(this, 5 x median) are rejected; `k3`, `tangential`:
    auto | hold | fit; `square_pixels`: fy = fx; `centred`: the principal point at the image centre;
    `fisheye`: the cameras fitted with the fisheye model ("*": every camera)."""

    outlier_px: float = 1.0
    k3: str = "auto"
    tangential: str = "auto"
    square_pixels: bool = False
    centred: bool = False
    fisheye: tuple[str, ...] = ()

    def check(self) -> None:
        from rig.errors import ConfigError

        if not self.outlier_px > 0:
            raise ConfigError(f"--outlier-px must be positive, got {self.outlier_px}")

    def check_cameras(self, cameras: list[str]) -> None:
        """Every camera named for the fisheye model has images."""
        from rig.errors import ConfigError

        for name in self.fisheye:
            if name != "*" and name not in cameras:
                raise ConfigError(f"--fisheye {name}: no images of camera '{name}' (cameras: {', '.join(cameras)})")

    def options(self, **more):
        """The solver's options (calibration.solve.Options), with `more` of them."""
        from calibration.solve import Options

        return Options(outlier_px=self.outlier_px, fix_k3=_HOLD[self.k3], fix_tangential=_HOLD[self.tangential],
                       square_pixels=self.square_pixels, centred=self.centred,
                       fisheye=True if "*" in self.fisheye else frozenset(self.fisheye), **more)


def detect(images, board):
    """The board's corners in every image (minutes for a few hundred images: call it after every
    check of the input and of where the result goes), with a status line."""
    from calibration.images import detect_images
    from rig.progress import StatusLine

    status = StatusLine()
    detections = detect_images(images, board, progress=lambda i, n: status.update(f"detecting the board: {i}/{n} images"))
    status.done()
    return detections
