"""The Table 1 columns for one view and their mean over views.

Two protocols, each a block of the same keys:

* ``masked``: object pixels only (the ground-truth mask): PSNR over them, SSIM map averaged over them.
* ``whole_image``: the official code's protocol: outside the mask both images are set to white
  (1.0; roughness too) and whole images are scored, so numbers compare with the paper's.

Albedo is aligned per image and channel by ``median(gt / pred)`` over the mask in linear space,
then scored in sRGB like the colours; specular and RGB are scored in sRGB, clipped to [0, 1].
Roughness MSE is on the roughness values themselves.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..io.images import linear_to_srgb
from .metrics import median_scale, mse, psnr, ssim

METRIC_KEYS = ("roughness_mse", "albedo_psnr", "albedo_ssim", "albedo_lpips", "specular_psnr", "specular_ssim",
               "specular_lpips", "rgb_psnr", "rgb_ssim", "rgb_lpips")
PROTOCOLS = ("masked", "whole_image")


@dataclass(frozen=True)
class ViewArrays:
    """One view as numpy arrays (linear; ``None`` where the ground truth lacks the map)."""

    rgb: np.ndarray | None
    """None: no colour (a material-only eval's prediction)"""
    albedo: np.ndarray | None
    roughness: np.ndarray | None
    specular: np.ndarray | None


def _white_outside(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    m = mask if img.ndim == 2 else mask[..., None]
    return np.where(m, img, 1.0)


def _colour_scores(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, protocol: str) -> tuple[float, float]:
    p, g = linear_to_srgb(pred), linear_to_srgb(gt)
    if protocol == "masked":
        return psnr(p, g, mask), ssim(p, g, mask)
    p, g = _white_outside(p, mask), _white_outside(g, mask)
    return psnr(p, g), ssim(p, g)


def view_scores(pred: ViewArrays, gt: ViewArrays, mask: np.ndarray) -> tuple[dict[str, dict], np.ndarray]:
    """Both protocols' scores for one view, and the albedo scale used (``(3,)``, ones without GT albedo)."""
    scale = np.ones(3, np.float32)
    aligned = None
    if gt.albedo is not None and pred.albedo is not None:
        scale = median_scale(pred.albedo, gt.albedo, mask)
        aligned = pred.albedo * scale
    blocks: dict[str, dict] = {}
    for protocol in PROTOCOLS:
        s: dict[str, float | None] = {k: None for k in METRIC_KEYS}
        if gt.roughness is not None and pred.roughness is not None:
            if protocol == "masked":
                s["roughness_mse"] = mse(pred.roughness, gt.roughness, mask)
            else:
                s["roughness_mse"] = mse(_white_outside(pred.roughness, mask), _white_outside(gt.roughness, mask))
        if aligned is not None:
            s["albedo_psnr"], s["albedo_ssim"] = _colour_scores(aligned, gt.albedo, mask, protocol)
        if gt.specular is not None and pred.specular is not None:
            s["specular_psnr"], s["specular_ssim"] = _colour_scores(pred.specular, gt.specular, mask, protocol)
        if gt.rgb is not None and pred.rgb is not None:
            s["rgb_psnr"], s["rgb_ssim"] = _colour_scores(pred.rgb, gt.rgb, mask, protocol)
        blocks[protocol] = s
    return blocks, scale


def mean_scores(views: list[dict[str, dict]]) -> dict[str, dict]:
    """Mean of each key over views (PSNR averaged per view, as papers do); ``None`` if no view has it."""
    out: dict[str, dict] = {}
    for protocol in PROTOCOLS:
        block: dict[str, float | None] = {}
        for k in METRIC_KEYS:
            vals = [v[protocol][k] for v in views if v[protocol][k] is not None and not math.isnan(v[protocol][k])]
            block[k] = float(np.mean(vals)) if vals else None
        out[protocol] = block
    return out
