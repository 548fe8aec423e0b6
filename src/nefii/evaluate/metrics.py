"""Image metrics of Table 1, as NeRF-style papers compute them.

PSNR and SSIM (11-tap Gaussian, sigma 1.5, scikit-image with ``use_sample_covariance=False``,
which matches the usual TensorFlow/NeRF implementation exactly) on images in ``[0, 1]``.
"Masked" variants score only object pixels: PSNR over the mask, SSIM map averaged over the mask.
LPIPS needs a pretrained backbone that cannot be loaded offline here: it is reported as
``None`` with :data:`LPIPS_UNAVAILABLE` as the reason.
"""
from __future__ import annotations

import math

import numpy as np
from skimage.metrics import structural_similarity

LPIPS_UNAVAILABLE = ("LPIPS needs pretrained VGG/AlexNet weights; none can be loaded offline "
                     "in this environment, so the column is n/a")


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """``-10 log10(MSE)`` over all pixels, or over ``mask`` (H, W) pixels; images in [0, 1]."""
    err = mse(pred, gt, mask)
    if math.isnan(err):
        return math.nan
    return math.inf if err == 0 else -10.0 * math.log10(err)


SSIM_PAD = 5
"""half the 11-tap window: scikit-image (and the NeRF code) average the SSIM map without this border"""


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Gaussian SSIM of (H, W[, C]) images in [0, 1]; with ``mask``, the SSIM map's mean over the mask
    (inside the same border-cropped region the unmasked mean uses)."""
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    channel_axis = -1 if pred.ndim == 3 else None
    mean, smap = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                       data_range=1.0, channel_axis=channel_axis, full=True)
    if mask is None:
        return float(mean)
    if smap.ndim == 3:
        smap = smap.mean(-1)
    inner = np.zeros_like(mask, dtype=bool)
    inner[SSIM_PAD:-SSIM_PAD, SSIM_PAD:-SSIM_PAD] = True
    m = mask & inner
    return float(smap[m].mean()) if m.any() else math.nan


def median_scale(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Per-channel ``median(gt / pred)`` over the mask (linear values): the albedo alignment of Table 1.

    Albedo from images is only defined up to a scale per channel shared with the light; the
    scale that best maps the prediction onto the ground truth is removed before scoring.
    Returns ``(C,)``; 1 where the mask is empty.
    """
    c = pred.shape[-1]
    if not mask.any():
        return np.ones(c, np.float32)
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    ratio = g / np.maximum(p, eps)
    return np.median(ratio, axis=0).astype(np.float32)


def mse(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared error over all pixels, or over ``mask`` (H, W) pixels; NaN for an empty mask."""
    err = (np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2
    if mask is not None:
        if not mask.any():
            return math.nan
        err = err[mask]
    return float(err.mean())
