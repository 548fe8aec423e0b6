"""Eval outputs: metrics.json / metrics.md with fixed names, per-view EXRs and PNG grids."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..io.atomic import write_text_atomic
from ..io.images import linear_to_srgb, write_png
from .metrics import LPIPS_UNAVAILABLE
from .table1 import METRIC_KEYS, PROTOCOLS

_LABELS = {"roughness_mse": "Roughness MSE", "albedo_psnr": "Albedo PSNR", "albedo_ssim": "Albedo SSIM",
           "albedo_lpips": "Albedo LPIPS", "specular_psnr": "Specular PSNR", "specular_ssim": "Specular SSIM",
           "specular_lpips": "Specular LPIPS", "rgb_psnr": "RGB PSNR", "rgb_ssim": "RGB SSIM", "rgb_lpips": "RGB LPIPS"}


def _clean(v):
    if isinstance(v, float) and (math.isnan(v) or math.isinf(v)):
        return None
    return v


def write_metrics(folder: Path, means: dict[str, dict], views: list[dict], notes: dict[str, str]) -> None:
    """``metrics.json`` = ``{"masked": {...}, "whole_image": {...}, "views": [...], "notes": {...}}``."""
    blob = {p: {k: _clean(means[p][k]) for k in METRIC_KEYS} for p in PROTOCOLS}
    blob["views"] = [{k: ({kk: _clean(vv) for kk, vv in v.items()} if isinstance(v, dict) else v)
                      for k, v in view.items()} for view in views]
    blob["notes"] = {"lpips": LPIPS_UNAVAILABLE, **notes}
    write_text_atomic(folder / "metrics.json", json.dumps(blob, indent=2) + "\n")
    write_text_atomic(folder / "metrics.md", metrics_markdown(means, notes))


def _fmt(k: str, v) -> str:
    if v is None:
        return "n/a"
    return f"{v:.4f}" if k.endswith("mse") or k.endswith("ssim") else f"{v:.2f}"


def metrics_markdown(means: dict[str, dict], notes: dict[str, str]) -> str:
    lines = ["# nefii eval", ""]
    for protocol, title in (("masked", "Object pixels (masked)"),
                            ("whole_image", "Whole image, white background (official protocol)")):
        lines += [f"## {title}", "", "| " + " | ".join(_LABELS[k] for k in METRIC_KEYS) + " |",
                  "|" + "---|" * len(METRIC_KEYS),
                  "| " + " | ".join(_fmt(k, means[protocol][k]) for k in METRIC_KEYS) + " |", ""]
    lines += ["Notes:", "", f"- LPIPS: {LPIPS_UNAVAILABLE}."]
    lines += [f"- {k}: {v}" for k, v in notes.items()]
    return "\n".join(lines) + "\n"


def tonemap_display(x: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear HDR -> [0, 1] for looking at (Reinhard), before sRGB encoding."""
    x = np.maximum(x * exposure, 0.0)
    return x / (1.0 + x)


def write_grid(path: Path, rows: list[tuple[np.ndarray, np.ndarray]], srgb_rows: list[bool]) -> None:
    """One PNG: a row per quantity, columns GT | ours | |error| (x4)."""
    tiles = []
    for (gt, pred), is_colour in zip(rows, srgb_rows):
        gt3 = gt if gt.ndim == 3 else np.repeat(gt[..., None], 3, -1)
        pr3 = pred if pred.ndim == 3 else np.repeat(pred[..., None], 3, -1)
        if is_colour:
            gt3, pr3 = linear_to_srgb(np.clip(gt3, 0, 1)), linear_to_srgb(np.clip(pr3, 0, 1))
        err = np.clip(np.abs(gt3 - pr3) * 4.0, 0, 1)
        tiles.append(np.concatenate([gt3, pr3, err], 1))
    write_png(path, np.concatenate(tiles, 0), srgb=False)
