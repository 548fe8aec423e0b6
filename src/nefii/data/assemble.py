"""Shared by the readers: read each view's image and mask, and assemble :class:`SceneData`."""
from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..errors import InputError
from .files import read_exposure, read_image, read_mask
from .scene import Cameras, GroundTruth, Relit, SceneData
from .validate import check_mask, check_size


@dataclass(frozen=True)
class View:
    """Where one view's files are."""

    image: Path
    """its image file"""
    mask: Path | None = None
    """its mask file; ``None``: the image's alpha, if every view has one, gives the mask"""


@dataclass(frozen=True)
class ViewStack:
    """The views' pixels, read and checked."""

    images: np.ndarray
    """``(N, H, W, 3)`` linear float32"""
    masks: np.ndarray | None
    """``(N, H, W)`` bool, or ``None`` without masks"""
    transparent: bool
    """the background is transparent (masks from alpha): its pixels show nothing"""
    clipped: np.ndarray | None
    """``(N, H, W)`` bool: pixels saturated in some channel (8/16-bit files); ``None`` when no file can clip"""
    exposure: np.ndarray | None = None
    """``(N,)`` each photo's exposure from its EXIF (:func:`read_exposure`); ``None`` unless every view has one"""


EXPOSURE_SPAN = 20.0
"""stops between the brightest and the darkest EXIF exposure beyond which the metadata is taken as wrong"""


def read_exposures(views: Sequence[View]) -> np.ndarray | None:
    """Each view's EXIF exposure when every view has one, else ``None`` (a warning when only some have
    one). Readers of photographs (nerfstudio, COLMAP) call it on the original files before undistorting
    them, so bad metadata leaves nothing written. Exposures spanning more than :data:`EXPOSURE_SPAN` stops
    are an :class:`InputError` naming the view farthest from the median."""
    found = [read_exposure(v.image) for v in views]
    have = [e is not None for e in found]
    if not any(have):
        return None
    if not all(have):
        missing = next(v for v, h in zip(views, have) if not h)
        warnings.warn(f"{missing.image}: no EXIF exposure, while {sum(have)} of {len(views)} views have one: "
                      "the exposure metadata is not used", stacklevel=3)
        return None
    ev = np.log2(np.array(found, dtype=np.float64))
    if ev.max() - ev.min() > EXPOSURE_SPAN:
        worst = int(np.argmax(np.abs(ev - np.median(ev))))
        raise InputError(views[worst].image, f"EXIF exposure is 2^{ev[worst] - np.median(ev):+.1f} times the views' "
                                             f"median: the views' exposures span {ev.max() - ev.min():.1f} stops, "
                                             f"more than {EXPOSURE_SPAN:.0f} (absurd metadata)")
    return np.array(found, dtype=np.float64)


def read_views(views: Sequence[View], exposure: np.ndarray | None = None) -> ViewStack:
    """Read every view's image and mask; ``exposure``: the photos' EXIF exposures, read by the caller
    (:func:`read_exposures`) from the original files before anything was made from them.

    Masks come from the mask files when views name them (then every view must), else from
    alpha > 0.5 when every image has an alpha channel and some alpha is below 1 (then the
    background is transparent: its pixels show nothing), else ``None``.
    Different sizes, NaN/inf pixels and empty masks raise :class:`InputError` naming the file.
    """
    if not views:
        raise InputError(None, "no views to read")
    rgbs, alphas, clips = [], [], []
    for v in views:
        img = read_image(v.image)
        if rgbs:
            check_size(img.rgb.shape, v.image, rgbs[0].shape[:2], views[0].image)
        rgbs.append(img.rgb)
        alphas.append(img.alpha)
        clips.append(np.zeros(img.rgb.shape[:2], bool) if img.clipped is None else img.clipped)
    size = rgbs[0].shape[:2]
    _warn_suspicious(views, rgbs, alphas)
    masks: list[np.ndarray] | None = None
    transparent = False
    if any(v.mask is not None for v in views):
        masks = []
        for v in views:
            if v.mask is None:
                raise InputError(v.image, "this view has no mask file while other views do")
            m = read_mask(v.mask)
            check_size(m.shape, v.mask, size, views[0].image)
            check_mask(m, v.mask)
            masks.append(m)
    elif all(a is not None for a in alphas) and any(bool((a < 1.0).any()) for a in alphas):
        masks = []
        transparent = True
        for v, a in zip(views, alphas):
            m = a > 0.5
            check_mask(m, v.image)
            masks.append(m)
    clipped = np.stack(clips) if any(c.any() for c in clips) else None
    return ViewStack(np.stack(rgbs), None if masks is None else np.stack(masks), transparent, clipped, exposure)


def _warn_suspicious(views: Sequence[View], rgbs: list[np.ndarray], alphas: list[np.ndarray | None]) -> None:
    """One warning each for what a dataset may mean but rarely does: negative pixels, and views without an
    alpha channel among views with one (then alpha gives no masks at all: the background counts as seen)."""
    negative = [(v, int((rgb < 0).any(-1).sum())) for v, rgb in zip(views, rgbs)]
    negative = [(v, n) for v, n in negative if n]
    if negative:
        total = sum(n for _, n in negative)
        warnings.warn(f"{negative[0][0].image}: {total} pixel(s) with negative values in {len(negative)} view(s); "
                      "trained on as they are", stacklevel=3)
    without = [v for v, a in zip(views, alphas) if a is None]
    if without and len(without) < len(views):
        warnings.warn(f"{without[0].image}: no alpha channel, while {len(views) - len(without)} other view(s) have "
                      f"one ({len(without)} without): no view's alpha is used as a mask, so the background "
                      "counts as visible everywhere", stacklevel=3)


def read_colour_stack(files: Sequence[Path], size: tuple[int, int]) -> torch.Tensor:
    """``(N, H, W, 3)`` linear straight colour of ``files`` (relit views, say), each checked to be ``size``
    = (H, W), the views' size."""
    rgbs = []
    for f in files:
        rgb = read_image(f).rgb
        check_size(rgb.shape, f, size, "the views")
        rgbs.append(rgb)
    return torch.from_numpy(np.stack(rgbs))


def frame_indices(stems: Sequence[str]) -> tuple[int, ...]:
    """The trailing integer of each stem (``r_12`` -> 12) when all have one and they are distinct,
    else the positions ``0..N-1``."""
    found = [re.search(r"(\d+)$", s) for s in stems]
    if all(found):
        idx = tuple(int(m.group(1)) for m in found)  # type: ignore[union-attr]
        if len(set(idx)) == len(idx):
            return idx
    return tuple(range(len(stems)))


def relative_name(path: Path, root: Path) -> str:
    """``path`` relative to ``root`` with POSIX separators."""
    return Path(os.path.relpath(path, root)).as_posix()


def make_scene(*, root: Path, split: str, fmt: str, views: Sequence[View], stack: ViewStack,
               K: Sequence[np.ndarray], c2w: Sequence[np.ndarray],
               indices: Sequence[int] | None = None, scene_to_source: np.ndarray | None = None,
               ground_truth: GroundTruth | None = None, mesh_path: Path | None = None,
               envmap: np.ndarray | None = None, relit: Sequence[Relit] = ()) -> SceneData:
    """Assemble validated numpy pieces into :class:`SceneData` (torch, CPU)."""
    images, masks = stack.images, stack.masks
    names = tuple(relative_name(v.image, root) for v in views)
    if indices is None:
        indices = frame_indices([v.image.name.split(".")[0] for v in views])
    cams = Cameras(K=torch.from_numpy(np.stack(K).astype(np.float64)),
                   c2w=torch.from_numpy(np.stack(c2w).astype(np.float64)),
                   height=int(images.shape[1]), width=int(images.shape[2]))
    return SceneData(
        images=torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)),
        masks=None if masks is None else torch.from_numpy(np.ascontiguousarray(masks, dtype=bool)),
        cameras=cams, names=names, indices=tuple(int(i) for i in indices), split=split, format=fmt,
        root=root,
        scene_to_source=torch.from_numpy(np.eye(4) if scene_to_source is None
                                         else np.asarray(scene_to_source, np.float64)),
        ground_truth=ground_truth, mesh_path=mesh_path,
        envmap=None if envmap is None else torch.from_numpy(np.ascontiguousarray(envmap, dtype=np.float32)),
        relit=tuple(relit), background_visible=not stack.transparent,
        clipped=None if stack.clipped is None else torch.from_numpy(stack.clipped),
        exposure=None if stack.exposure is None else torch.from_numpy(stack.exposure),
    )
