"""Stage 1's metric scale, checked against the two sources themselves.

A backbone's depth can be right in shape and off in scale: on held-out simulator takes the stereo
backbone's depth was 0.94 to 1.10 times the truth per take (the same on every frame set of a take),
while its error once divided by that factor was about 5 %. The two source images tell the scale:
each view's points, scaled by k about its own camera centre, re-project the other image onto its
own only at the right k. For `candidates` factors k, geometric between 1 / (1 + r) and 1 + r, both
views are warped into each other and compared (0.85 (1 - SSIM) / 2 + 0.15 L1, the self-supervised
monocular-depth photometric error, on the pixels that land inside the other image); the factor is
the softmin-weighted geometric mean of the candidates, with a temperature that follows the spread of
the errors, so it moves continuously with the inputs and no weight is learned. Both point maps are
then scaled by it about their own cameras. The errors are computed in double precision: the softmin
follows differences of parts in a million between them, where float32's rounding differs between
torch and ONNX Runtime (see `errors`).
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.model.geometry import in_image, invert_pose, normalise_pixels, project, transform_points

# The softmin's temperature as a fraction of (mean - min) of the candidates' errors: small enough to
# follow the minimum, large enough to interpolate between neighbouring candidates.
SHARPNESS = 0.05


def _box3(x: torch.Tensor) -> torch.Tensor:
    """The mean over each pixel's 3x3 window within the image (B, C, H, W), as avg_pool2d(x, 3, 1, 1,
    count_include_pad=False) computes it, but from slices and sums: ONNX Runtime's AveragePool has no
    double kernel, and the search's errors are computed in double (see ScaleSearch.errors)."""
    h, w = x.shape[-2:]
    p = F.pad(x, (1, 1, 1, 1))
    rows = p[..., 0:h, :] + p[..., 1:h + 1, :] + p[..., 2:h + 2, :]
    box = rows[..., 0:w] + rows[..., 1:w + 1] + rows[..., 2:w + 2]
    # Pixels per window: 3 inside, 2 on the border row or column.
    ny = torch.full((h, 1), 3.0, dtype=x.dtype, device=x.device)
    ny[0], ny[-1] = 2.0, 2.0
    nx = torch.full((1, w), 3.0, dtype=x.dtype, device=x.device)
    nx[:, 0], nx[:, -1] = 2.0, 2.0
    return box / ny / nx  # two small divisors: their (H, W) product would be a constant in the export


def _ssim_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(1 - SSIM) / 2 per pixel over 3x3 windows (B, 1, H, W), averaged over the channels. Not the
    training loss's SSIM (inference/train/losses.py, 11x11 Gaussian): the model does not import the
    trainer, and a 3x3 box over 21 candidates x 2 views is the cheaper, local one monocular-depth
    photometric errors use."""
    mu_a, mu_b = _box3(a), _box3(b)
    var_a = _box3(a * a) - mu_a * mu_a
    var_b = _box3(b * b) - mu_b * mu_b
    cov = _box3(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2))
    return ((1.0 - ssim) / 2.0).clamp(0.0, 1.0).mean(dim=1, keepdim=True)


class ScaleSearch(nn.Module):
    def __init__(self, candidates: int, search_range: float, floor: float = 0.0):
        """`floor`: a part of the mean error added to the softmin's temperature. Where the candidates'
        errors lie within parts in a thousand of each other (no factor fits clearly, as on two
        unrelated images) and two factors far apart nearly tie, a temperature of 0.05 x (mean -
        min) alone lets the factor swing between them with the float rounding of stage 1's points
        (ONNX Runtime against torch: 6.8e-6 of the factor, 2.7e-3 of the image); the floor spreads
        the weights there. Where a factor fits (simulator takes: mean - min at least 5 % of the
        mean) it barely changes them. It trades: a flat curve with one clear best candidate
        follows the rounding a little more than without it (tests/inference/test_model_scale_search.py)."""
        super().__init__()
        self.floor = float(floor)
        a = math.log1p(search_range)
        self.register_buffer("log_factors", torch.linspace(-a, a, candidates), persistent=False)

    def errors(self, points_self: torch.Tensor, image_self: torch.Tensor, image_other: torch.Tensor,
               self_to_other: torch.Tensor, other_K: torch.Tensor) -> torch.Tensor:
        """Photometric error (B, N) of one view's points (its own camera frame, (B, 3, H, W)) scaled
        by each candidate factor and re-projected into the other view."""
        b, _, h, w = points_self.shape
        n = self.log_factors.shape[0]
        k = torch.exp(self.log_factors).reshape(1, n, 1, 1, 1)
        pts = (points_self[:, None] * k).reshape(b * n, 3, h, w)
        rep = lambda x: x[:, None].expand(b, n, *x.shape[1:]).reshape(b * n, *x.shape[1:])  # noqa: E731
        uv, z = project(transform_points(rep(self_to_other), pts), rep(other_K))
        visible = in_image(uv, z, w, h)
        warped = F.grid_sample(rep(image_other), normalise_pixels(uv, w, h), mode="bilinear", padding_mode="zeros", align_corners=False)
        # The error in double precision: the 21 candidates' errors differ by parts in a thousand,
        # and float32's rounding of the SSIM terms (1e-7 of an error of 0.4, in a direction that
        # differs between torch and ONNX Runtime) moved the factor by 5e-6, which the edges of
        # the target view turn into 5e-3 of image. In double the factor agrees within 1e-8.
        warped, own, visible = warped.double(), rep(image_self).double(), visible.double()
        err = 0.85 * _ssim_error(warped, own) + 0.15 * (warped - own).abs().mean(dim=1, keepdim=True)
        per = (err * visible).flatten(1).sum(1) / visible.flatten(1).sum(1).clamp(min=1.0)
        return per.reshape(b, n)

    def forward(self, points_left: torch.Tensor, points_right: torch.Tensor, left_image: torch.Tensor, right_image: torch.Tensor,
                left_K: torch.Tensor, right_K: torch.Tensor, right_to_left: torch.Tensor) -> torch.Tensor:
        """The scale factor (B,) for point maps in the left camera frame (coarse images and intrinsics)."""
        left_to_right = invert_pose(right_to_left)
        right_own = transform_points(left_to_right, points_right)
        e = self.errors(points_left, left_image, right_image, left_to_right, right_K) + self.errors(right_own, right_image, left_image, right_to_left, left_K)
        low = e.min(dim=1, keepdim=True).values
        mean = e.mean(dim=1, keepdim=True)
        temperature = SHARPNESS * (mean - low) + self.floor * mean + 1e-6
        weights = torch.softmax(-(e - low) / temperature, dim=1)
        return torch.exp((weights * self.log_factors.to(e.dtype).reshape(1, -1)).sum(dim=1)).to(points_left.dtype)


def rescale(points_left: torch.Tensor, points_right: torch.Tensor, factor: torch.Tensor, right_to_left: torch.Tensor):
    """Both point maps (left camera frame) scaled by `factor` (B,) about their own camera centres."""
    k = factor.reshape(-1, 1, 1, 1)
    centre = right_to_left[:, :3, 3].reshape(-1, 3, 1, 1)  # the right camera's centre in the left frame
    return points_left * k, centre + (points_right - centre) * k
