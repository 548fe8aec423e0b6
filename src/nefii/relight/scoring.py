"""What ``nefii relight`` states and scores: the albedo scale, PSNR/SSIM (and Stanford-ORB's PSNR-H/L,
:mod:`nefii.evaluate.stanford_orb`) against relit ground truth, ``metrics.json`` (one entry per output
folder, merged), and the tone curve of its PNGs.

Albedo from images is known only up to a scale per channel shared with the light (Table 1 aligns
it before scoring). Relighting with a new, known environment inherits that scale, so the scale
eval found is applied to the albedo before path tracing (clamped to [0, 1]) and written down:
the mean over test views of the per-view ``albedo_scale`` in ``RUN/eval/metrics.json``, or, if
eval has not run, the same median-ratio scale computed here against the ground-truth albedo.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..camera import pixel_rays
from ..data.scene import SceneData
from ..evaluate.metrics import median_scale, psnr, ssim
from ..raycast.base import Geometry, Rays
from ..io.atomic import write_text_atomic
from ..io.images import linear_to_srgb
from ..render.brdf import Material
from .pathtracer import MaterialFn

PROTOCOL = ("'psnr' and 'ssim': object pixels of the ground-truth mask, straight colour, sRGB-encoded after "
            "clipping to [0, 1]; every score of an entry is the mean over its views")
TONE_KNEE = 0.8
"""the PNG tone curve is the identity below this linear value and rolls off smoothly to 1 above it"""


# --------------------------------------------------------------------------- the albedo scale


def albedo_scale_from_eval(run: Path) -> np.ndarray | None:
    """Mean per channel of the per-view ``albedo_scale`` that ``nefii eval`` wrote, if it has run."""
    path = run / "eval" / "metrics.json"
    if not path.is_file():
        return None
    try:
        scales = [v["albedo_scale"] for v in json.loads(path.read_text())["views"]]
        arr = np.asarray(scales, dtype=np.float64)
    except (ValueError, KeyError, TypeError):
        return None
    if arr.ndim != 2 or arr.shape[1] != 3 or not np.isfinite(arr).all():
        return None
    return arr.mean(0)


@torch.no_grad()
def albedo_scale_from_ground_truth(material: MaterialFn, geometry: Geometry, scene: SceneData,
                                   device: torch.device) -> np.ndarray | None:
    """Eval's alignment computed here: per view ``median(gt / pred)`` over the mask at the pixel centres'
    first hits, then the mean over views. ``None`` without ground-truth albedo."""
    gt = scene.ground_truth
    if gt is None or gt.albedo is None:
        return None
    H, W = scene.height, scene.width
    scales = []
    for v in range(len(scene)):
        o, d = pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], H, W)
        hit = geometry.intersect(Rays(o.reshape(-1, 3).float().to(device), d.reshape(-1, 3).float().to(device)))
        pred = torch.zeros(H * W, 3, device=device)
        for c in hit.valid.nonzero().squeeze(-1).split(1 << 16):
            pred[c] = material(hit.position[c], hit.lookup_normal[c]).albedo.float()
        mask = hit.valid.cpu().numpy().reshape(H, W)
        mask &= (gt.mask[v] if gt.mask is not None else
                 scene.masks[v] if scene.masks is not None else torch.ones(H, W, dtype=torch.bool)).numpy()
        scales.append(median_scale(pred.cpu().numpy().reshape(H, W, 3), gt.albedo[v].numpy(), mask))
    return np.mean(scales, 0)


def scaled_material(material: MaterialFn, scale: np.ndarray | None) -> MaterialFn:
    """``(x, lookup_normal) -> Material(clamp(scale * albedo, 0, 1), roughness)``; ``material`` itself without
    a scale."""
    if scale is None:
        return material

    def scaled(x: torch.Tensor, n: torch.Tensor) -> Material:
        m = material(x, n)
        s = torch.as_tensor(scale, dtype=m.albedo.dtype, device=m.albedo.device)
        return Material((m.albedo * s).clamp(0.0, 1.0), m.roughness, m.brdf)

    return scaled


# --------------------------------------------------------------------------- scores and metrics.json


def score_view(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """PSNR and SSIM of straight linear colours over ``mask``, in sRGB clipped to [0, 1]."""
    p, g = linear_to_srgb(pred), linear_to_srgb(gt)
    return psnr(p, g, mask), ssim(p, g, mask)


def _finite_or_none(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


SCORES = ("psnr", "ssim", "psnr_h", "psnr_l")
"""the per-view scores an entry averages (where its views have them)"""


def metrics_entry(views: list[dict], **stated) -> dict:
    """``{"psnr", "ssim", "psnr_h", "psnr_l" (means over views, those the views have), "views": [...],
    **stated}`` with NaN/inf as null."""
    def mean(key: str) -> float | None:
        vals = [v[key] for v in views if v.get(key) is not None and math.isfinite(v[key])]
        return float(np.mean(vals)) if vals else None

    clean = [{k: (_finite_or_none(x) if isinstance(x, float) else x) for k, x in v.items()} for v in views]
    means = {key: mean(key) for key in SCORES if any(key in v for v in views)}
    return {**means, "views": clean, **stated}


def merge_metrics(path: Path, env: str, entry: dict) -> dict:
    """Put ``entry`` under ``env`` in the JSON object at ``path`` (other environments kept); atomic."""
    blob: dict = {}
    if path.is_file():
        try:
            blob = json.loads(path.read_text())
        except json.JSONDecodeError:
            blob = {}
        if not isinstance(blob, dict):
            blob = {}
    blob[env] = entry
    write_text_atomic(path, json.dumps(dict(sorted(blob.items())), indent=2) + "\n")
    return blob


# --------------------------------------------------------------------------- pictures


def tone_map(x: np.ndarray, knee: float = TONE_KNEE) -> np.ndarray:
    """Linear colour -> [0, 1): the identity up to ``knee``, then ``k + (1 - k)(1 - e^{-(x - k)/(1 - k)})``
    (continuous slope 1 at the knee), per channel: highlights roll off instead of clipping."""
    x = np.maximum(np.asarray(x, np.float32), 0.0)
    over = knee + (1.0 - knee) * -np.expm1(-(x - knee) / (1.0 - knee))
    return np.where(x <= knee, x, over).astype(np.float32)
