"""Photographs larger than a fit needs, made smaller once at load time (a phone's 4032 x 3024 JPEGs).

Each image is averaged over ``f x f`` blocks of pixels in linear light (what a sensor with ``f`` times
larger pixels would have recorded); the intrinsics follow exactly, because nefii puts pixel ``(i, j)``'s
centre at ``(j + 0.5, i + 0.5)``: the block edges at multiples of ``f`` land on the new pixels' edges, so
``fx, fy, cx, cy`` are all divided by ``f``. Rows and columns beyond the last whole block are cropped
from the right and bottom (which leaves ``K`` unchanged). A mask keeps a block that is mostly object; a
block with any clipped pixel is clipped (its average is not the scene's).
"""
from __future__ import annotations

import dataclasses
import math

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from .scene import Cameras, SceneData


def factor_for(height: int, width: int, max_side: int) -> int:
    """The smallest integer ``f`` that brings the larger side to ``max_side`` or less (``max_side`` 0: 1)."""
    if max_side <= 0:
        return 1
    return max(1, math.ceil(max(height, width) / max_side))


def block_mean(x: Float[Tensor, "N H W C"], f: int) -> Float[Tensor, "N H/f W/f C"]:
    """The mean over ``f x f`` blocks (``H`` and ``W`` multiples of ``f``)."""
    n, h, w, c = x.shape
    return x.reshape(n, h // f, f, w // f, f, c).mean(dim=(2, 4))


def _blocks(x: Bool[Tensor, "N H W"], f: int) -> Float[Tensor, "N H/f W/f"]:
    return block_mean(x[..., None].float(), f)[..., 0]


def downscaled(scene: SceneData, max_side: int) -> tuple[SceneData, int]:
    """``scene`` with its larger image side at most ``max_side`` pixels, and the factor used (1: unchanged).

    Only the images, masks, clipped pixels and cameras are resampled; a scene with ground-truth maps or
    relit views (scoring data, never photographs) is returned as it is."""
    f = factor_for(scene.height, scene.width, max_side)
    if f == 1 or scene.ground_truth is not None or scene.relit:
        return scene, 1
    h, w = scene.height // f * f, scene.width // f * f
    K = scene.cameras.K.clone()
    K[:, :2, :] /= f
    crop = (slice(None), slice(0, h), slice(0, w))
    return dataclasses.replace(
        scene,
        images=block_mean(scene.images[crop], f).contiguous(),
        masks=None if scene.masks is None else _blocks(scene.masks[crop], f) >= 0.5,
        clipped=None if scene.clipped is None else _blocks(scene.clipped[crop], f) > 0,
        cameras=Cameras(K=K, c2w=scene.cameras.c2w, height=h // f, width=w // f),
    ), f


def training_images(scene: SceneData, max_side: int) -> tuple[SceneData, str | None]:
    """:func:`downscaled` for a stage that trains on ``scene``, and the line that says what it did (``None``
    when the images are used as they are)."""
    small, f = downscaled(scene, max_side)
    if f == 1:
        return scene, None
    return small, (f"images averaged down {f}x: {scene.width}x{scene.height} -> {small.width}x{small.height} "
                   f"(max_image_side {max_side})")
