"""Pinhole cameras. Internal convention: OpenCV axes (x right, y down, z forward),
camera-to-world 4x4 matrices, intrinsics ``K`` in pixels with pixel centres at ``+0.5``."""
from __future__ import annotations

import torch
from jaxtyping import Float, Int
from torch import Tensor

from .render.frame import normalize

OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
"""``c2w_cv = c2w_gl @ OPENGL_TO_OPENCV`` (flip camera y and z); the same matrix converts back."""


def look_at(eye: Float[Tensor, "3"], target: Float[Tensor, "3"],
            up: Float[Tensor, "3"]) -> Float[Tensor, "4 4"]:
    """OpenCV camera-to-world matrix of a camera at ``eye`` looking at ``target``."""
    z = normalize(target - eye)
    x = normalize(torch.linalg.cross(z, up))
    y = torch.linalg.cross(z, x)
    c2w = torch.eye(4, dtype=eye.dtype, device=eye.device)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def intrinsics_from_fov(fov_x: float, width: int, height: int) -> Float[Tensor, "3 3"]:
    """``K`` for a horizontal field of view ``fov_x`` (radians), square pixels, centred principal point."""
    f = 0.5 * width / torch.tan(torch.tensor(0.5 * fov_x, dtype=torch.float64))
    return torch.tensor([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float64)


def pixel_rays(c2w: Float[Tensor, "4 4"], K: Float[Tensor, "3 3"], height: int,
               width: int) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 3"]]:
    """Origins and unit directions through the centre of every pixel (OpenCV convention)."""
    pixel = torch.arange(height * width, device=c2w.device)
    o, d = jittered_pixel_rays(c2w, K, width, pixel, torch.full((height * width, 2), 0.5, dtype=c2w.dtype,
                                                                device=c2w.device))
    return o.reshape(height, width, 3), d.reshape(height, width, 3)


def jittered_pixel_rays(c2w: Float[Tensor, "4 4"], K: Float[Tensor, "3 3"], width: int,
                        pixel: Int[Tensor, " P"], u: Float[Tensor, "P 2"]) -> tuple[Float[Tensor, "P 3"], Float[Tensor, "P 3"]]:
    """Origins and unit directions through ``(j + u0, i + u1)`` of flat pixel ``i W + j`` (OpenCV camera,
    ``K`` in pixels): box-filtered pixels, as renderers make ground truth."""
    c2w, K = c2w.to(u), K.to(u)
    i, j = pixel // width, pixel % width
    px, py = j.to(u.dtype) + u[:, 0], i.to(u.dtype) + u[:, 1]
    d_cam = torch.stack([(px - K[0, 2]) / K[0, 0], (py - K[1, 2]) / K[1, 1], torch.ones_like(px)], -1)
    d = normalize(d_cam @ c2w[:3, :3].T)
    return c2w[:3, 3].expand_as(d), d
