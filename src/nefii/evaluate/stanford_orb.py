"""Stanford-ORB's image scores, PSNR-H and PSNR-L, as its evaluation code computes them (the ``calc_PSNR``
of ``orb/utils/metrics.py`` with the settings of ``compute_similarity`` in ``orb/utils/test.py``).

For one view, with the ground-truth mask ``m``:

1. ``m`` is eroded by a 5 x 5 square (OpenCV's ``erode``: the border does not erode); prediction ``p``
   and truth ``g`` are multiplied by it, and ``g < 0`` set to 0.
2. PSNR-H only: both are multiplied by ``k = mean(srgb(clip(g, 0, 1))) / mean(clip(g, 0, 1))`` (means
   over every pixel and channel; skipped when the second is <= 1e-8): linear HDR is dark, this brings it
   to about the brightness of its sRGB encoding.
3. Relighting is scored up to a scale per channel: ``p_c *= s_c`` with the least-squares
   ``s_c = sum(g_c p_c) / sum(p_c^2)`` over the eroded mask (a channel with ``sum(p_c^2) <= 1e-6``
   gets ``s_c = mean(g_c)``, as if it were 1; it stays black).
4. Both are clipped to ``[0, 4]`` (PSNR-H) or ``[0, 1]`` and then sRGB-encoded (PSNR-L).
5. ``MSE`` is the mean over **all** ``H x W x 3`` values (pixels off the mask are 0 in both, so a view's
   score depends on how much of it the object covers); ``PSNR = -10 log10(MSE)`` (peak 1), and never less
   than the PSNR a uniform 0.5 over the eroded mask would get.

The benchmark scores at 512 x 512 (its 2048 x 2048 photographs shrunk by OpenCV's ``INTER_AREA``, a box
filter for whole factors; masks thresholded at 0.5 after): :func:`relight_scores` box-filters larger
images to that size when their sides are whole multiples of it, and scores others as they are.
Per scene the benchmark averages the views; over scenes, the scenes. LPIPS and its SSIM (3 x 3 window on
the PSNR-L images) are not computed here.
"""
from __future__ import annotations

import math

import numpy as np

from ..io.images import linear_to_srgb

BENCHMARK_RESOLUTION = 512
"""the size Stanford-ORB scores at"""
ERODE = 5
"""side of the square the mask is eroded by"""
HDR_MAX = 4.0
"""PSNR-H clips at this (after the brightness normalisation)"""
LDR_MAX = 1.0
"""PSNR-L clips at this (linear, before sRGB encoding)"""
BLACK = 1e-6
"""a channel whose ``sum(p^2)`` over the mask is at most this has no scale of its own"""

PROTOCOL = ("Stanford-ORB relighting: 'psnr_h' and 'psnr_l' as its orb/utils/metrics.py with scale_invariant=True: "
            "mask eroded 5x5, per-channel least-squares scale of the prediction onto the truth, clipped to [0, 4] "
            "(H, after the mean sRGB/linear brightness normalisation) or [0, 1] then sRGB (L), MSE over the whole "
            "image, floored at a uniform 0.5; images larger than 512x512 box-filtered to it when whole multiples")


def erode(mask: np.ndarray, size: int = ERODE) -> np.ndarray:
    """Binary erosion of an ``(H, W)`` mask by a ``size x size`` square; outside the image counts as inside
    (OpenCV's default border for erosion)."""
    r = size // 2
    padded = np.pad(np.asarray(mask, bool), r, constant_values=True)
    h, w = mask.shape
    out = np.ones((h, w), bool)
    for dy in range(size):
        for dx in range(size):
            out &= padded[dy:dy + h, dx:dx + w]
    return out


def brightness_factor(g: np.ndarray) -> float:
    """PSNR-H's ``k = mean(srgb(clip(g, 0, 1))) / mean(clip(g, 0, 1))``; 1 when the second is <= 1e-8."""
    c = np.clip(g, 0.0, 1.0)
    lin = float(c.mean())
    return float(linear_to_srgb(c).astype(np.float64).mean()) / lin if lin > 1e-8 else 1.0


def channel_scale(p: np.ndarray, g: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(3,)`` least-squares ``s_c = sum(g_c p_c) / sum(p_c^2)`` over ``mask``; for a black channel
    (``sum(p_c^2) <= 1e-6``) the same with ``p_c = 1``, i.e. ``mean(g_c)``."""
    pm, gm = p[mask], g[mask]
    num, den = (gm * pm).sum(0), (pm ** 2).sum(0)
    black = den <= BLACK
    return np.where(black, gm.sum(0) / max(len(gm), 1), num / np.where(black, 1.0, den))


def _psnr(mse: float) -> float:
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def scale_invariant_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, *, hdr: bool) -> float:
    """PSNR-H (``hdr``) or PSNR-L of one view: ``pred``, ``gt`` ``(H, W, 3)`` linear, ``mask`` ``(H, W)``
    bool (not yet eroded). NaN when the eroded mask is empty."""
    m = erode(mask)
    if not m.any():
        return math.nan
    mf = m[..., None].astype(np.float64)
    p = np.asarray(pred, np.float64) * mf
    g = np.maximum(np.asarray(gt, np.float64) * mf, 0.0)
    if hdr:
        k = brightness_factor(g)
        p, g = p * k, g * k
    p = p * channel_scale(p, g, m)
    top = HDR_MAX if hdr else LDR_MAX
    p, g = np.clip(p, 0.0, top), np.clip(g, 0.0, top)
    if not hdr:
        p, g = linear_to_srgb(p).astype(np.float64), linear_to_srgb(g).astype(np.float64)
    mse = float(((p - g) ** 2).mean())
    floor = float(((0.5 * mf - g) ** 2).mean())
    return max(_psnr(mse), _psnr(floor))


def box_downsample(x: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` blocks of an ``(H, W[, C])`` array whose sides are multiples of it."""
    h, w = x.shape[:2]
    blocks = x.reshape(h // factor, factor, w // factor, factor, *x.shape[2:])
    return blocks.mean(axis=(1, 3))


def benchmark_factor(height: int, width: int, resolution: int = BENCHMARK_RESOLUTION) -> int:
    """The whole factor that shrinks ``height x width`` to ``resolution`` on both sides; 1 if there is none."""
    if height == width and height > resolution and height % resolution == 0:
        return height // resolution
    return 1


def relight_scores(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray,
                   resolution: int = BENCHMARK_RESOLUTION) -> dict[str, float]:
    """``{"psnr_h", "psnr_l"}`` of one relit view (linear ``(H, W, 3)``, ``mask`` ``(H, W)`` bool), at the
    benchmark's resolution where the images are whole multiples of it."""
    f = benchmark_factor(mask.shape[0], mask.shape[1], resolution)
    if f > 1:
        pred, gt = box_downsample(np.asarray(pred, np.float64), f), box_downsample(np.asarray(gt, np.float64), f)
        mask = box_downsample(np.asarray(mask, np.float64), f) > 0.5
    return {"psnr_h": scale_invariant_psnr(pred, gt, mask, hdr=True),
            "psnr_l": scale_invariant_psnr(pred, gt, mask, hdr=False)}
