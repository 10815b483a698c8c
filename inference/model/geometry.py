"""Camera geometry in torch, written with ops that export to ONNX.

Conventions follow calibration.camera (OpenCV): pixel centres at integer coordinates, x right, y down,
z forward; a pose is the 4x4 world-to-camera matrix [R t; 0 1]. Batched: K (B,3,3), pose (B,4,4),
point maps (B,3,H,W).

torch.linalg.inv does not export, so inverses are closed-form: rigid transforms by transposition,
3x3 matrices by the adjugate. Small matrix products are written as elementwise multiply-adds in a
fixed order rather than matmuls: then torch and ONNX Runtime compute the same floats bit for bit
(BLAS kernels sum in their own orders), which matters where a result is sensitive to the last bits
of a projection (the rim of a splat kernel).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def inverse_3x3(m: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 3, 3) matrices through the adjugate (exportable; no linalg)."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    g, h, i = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    co_a = e * i - f * h
    co_b = -(d * i - f * g)
    co_c = d * h - e * g
    det = a * co_a + b * co_b + c * co_c
    adj = torch.stack(
        [
            torch.stack([co_a, -(b * i - c * h), b * f - c * e], dim=-1),
            torch.stack([co_b, a * i - c * g, -(a * f - c * d)], dim=-1),
            torch.stack([co_c, -(a * h - b * g), a * e - b * d], dim=-1),
        ],
        dim=-2,
    )
    return adj / det[..., None, None]


def matmul_small(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a @ b for small matrices (..., n, k) @ (..., k, m) as k elementwise multiply-adds in order."""
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for i in range(1, a.shape[-1]):
        out = out + a[..., :, i : i + 1] * b[..., i : i + 1, :]
    return out


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid (..., 4, 4) transforms: [R t] -> [R^T, -R^T t]."""
    r = pose[..., :3, :3]
    t = pose[..., :3, 3:]
    rt = r.transpose(-1, -2)
    top = torch.cat([rt, -matmul_small(rt, t)], dim=-1)
    bottom = pose[..., 3:, :]  # [0 0 0 1]
    return torch.cat([top, bottom], dim=-2)


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The rigid transform a after b, (..., 4, 4)."""
    return matmul_small(a, b)


def relative_pose(to_pose: torch.Tensor, from_pose: torch.Tensor) -> torch.Tensor:
    """The transform taking points from camera `from` to camera `to` (both world-to-camera poses)."""
    return compose(to_pose, invert_pose(from_pose))


def camera_centre_distance(pose_a: torch.Tensor, pose_b: torch.Tensor) -> torch.Tensor:
    """Distance between two camera centres (the baseline), shape (B,)."""
    rel = relative_pose(pose_b, pose_a)
    return torch.sqrt((rel[..., :3, 3] ** 2).sum(-1))


def scale_intrinsics(K: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics of the same camera resampled by (sx, sy), keeping the pixel-centre convention.

    Built from K's own rows (its last row is (0, 0, 1), so a multiple of it adds to the principal
    point alone): no constant tensor is made per call, which on a GPU was a blocking host copy on
    every frame and cannot be captured in a CUDA graph."""
    last = K[..., 2, :]
    return torch.stack((K[..., 0, :] * sx + last * (0.5 * sx - 0.5), K[..., 1, :] * sy + last * (0.5 * sy - 0.5), last), dim=-2)


def resize_intrinsics(K: torch.Tensor, from_size: tuple[int, int], to_size: tuple[int, int]) -> torch.Tensor:
    return scale_intrinsics(K, to_size[0] / from_size[0], to_size[1] / from_size[1])


def pixel_grid(width: int, height: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Homogeneous pixel coordinates (3, H, W): rows u, v, 1."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u, v, torch.ones_like(u)], dim=0)


def pixel_rays(K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Unit-z ray directions (B, 3, H, W) of every pixel of a pinhole camera."""
    grid = pixel_grid(width, height, K.dtype, K.device)
    ki = inverse_3x3(K)[..., None, None]  # (B, 3, 3, 1, 1)
    return ki[:, :, 0] * grid[0] + ki[:, :, 1] * grid[1] + ki[:, :, 2] * grid[2]  # (B, 3, H, W)


def unproject_depth(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Depth maps (B, 1, H, W) (z along the axis) to camera-frame point maps (B, 3, H, W)."""
    _, _, h, w = depth.shape
    return pixel_rays(K, w, h) * depth


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (B, 4, 4) rigid transforms to point maps (B, 3, ...)."""
    b = points.shape[0]
    flat = points.reshape(b, 1, 3, -1)
    m = T[:, :3, :, None]  # (B, 3, 4, 1)
    out = m[:, :, 0] * flat[:, :, 0] + m[:, :, 1] * flat[:, :, 1] + m[:, :, 2] * flat[:, :, 2] + m[:, :, 3]
    return out.reshape(points.shape)


def project(points: torch.Tensor, K: torch.Tensor, min_depth: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame points (B, 3, ...) to pixels (B, 2, ...) and depth z (B, 1, ...)."""
    b = points.shape[0]
    flat = points.reshape(b, 3, -1)
    z = flat[:, 2:3]
    zs = torch.where(z.abs() < min_depth, torch.full_like(z, min_depth), z)
    x = flat[:, 0:1] / zs
    y = flat[:, 1:2] / zs
    u = K[:, 0, 0, None, None] * x + K[:, 0, 1, None, None] * y + K[:, 0, 2, None, None]
    v = K[:, 1, 1, None, None] * y + K[:, 1, 2, None, None]
    uv = torch.cat([u, v], dim=1)
    shape = points.shape[2:]
    return uv.reshape(b, 2, *shape), z.reshape(b, 1, *shape)


def normalise_pixels(uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Pixels (B, 2, H, W) to grid_sample coordinates (B, H, W, 2) (align_corners=False)."""
    gx = (2.0 * uv[:, 0] + 1.0) / width - 1.0
    gy = (2.0 * uv[:, 1] + 1.0) / height - 1.0
    return torch.stack([gx, gy], dim=-1)


def in_image(uv: torch.Tensor, z: torch.Tensor, width: int, height: int, ramp: float = 1.0) -> torch.Tensor:
    """How much a projection lies inside the image, in front of the camera: 1 inside, 0 outside,
    a linear ramp over `ramp` pixels inward from the border pixel's outer edge (B, 1, ...).
    Continuous, so that float rounding of a projection near the border cannot switch a pixel
    between sources (torch/ONNX Runtime parity); a wider ramp is gentler still."""
    u, v = uv[:, 0:1], uv[:, 1:2]
    inside_u = torch.minimum(u + 0.5, width - 0.5 - u)
    inside_v = torch.minimum(v + 0.5, height - 0.5 - v)
    if ramp != 1.0:
        inside_u = inside_u / ramp
        inside_v = inside_v / ramp
    return inside_u.clamp(0.0, 1.0) * inside_v.clamp(0.0, 1.0) * (z > 1e-6).to(uv.dtype)


def sample(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample (B, C, H, W) at pixels uv (B, 2, h, w) given in that image's own pixel frame."""
    _, _, h, w = image.shape
    grid = normalise_pixels(uv, w, h)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)


def warp_from_source(
    source: torch.Tensor,
    source_K: torch.Tensor,
    target_to_source: torch.Tensor,
    target_points: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample a source map at the projections of target-frame points (B, 3, h, w).

    `source_K` is given for the source map's own size. Returns the sampled values (B, C, h, w) and
    the visibility (B, 1, h, w) (in front of the source camera and inside its image, see in_image).
    """
    _, _, sh, sw = source.shape
    pts = transform_points(target_to_source, target_points)
    uv, z = project(pts, source_K)
    return sample(source, uv), in_image(uv, z, sw, sh)
