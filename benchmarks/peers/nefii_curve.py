"""nefii's albedo PSNR against fitting time: the ``cpu`` preset's fit, re-run in process with snapshots.

``nefii fit`` keeps no history of its material, so the curve comes from a second run of the same
recipe, set up as ``nefii fit`` sets it up (``nefii.fit.session.prepare_fit``), then
``Trainer.train_step`` until ``cfg.steps``. Every ``every`` steps the clock stops and the material is
decoded at the test views' sub-pixel hits (``nefii.fit.model.material_at``), averaged per pixel and
scored. It writes no checkpoints, previews or logs, so its steps are a little cheaper than ``nefii fit``'s; its last point is
the quantity the quality run's albedo PSNR measures (same seed, same code).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nefii.cli.common import set_threads
from nefii.data import load_scene
from nefii.fit.config import FitConfig, resolve_config
from nefii.fit.model import material_at
from nefii.fit.session import prepare_fit

from .hits import cast_test_views, material_scores, positions, split_views


@dataclass
class CurvePoint:
    step: int
    fit_s: float
    scores: dict[str, float]


def run_curve(data: Path, threads: int = 1, every: int = 100, overrides: list[str] | None = None,
              max_steps: int | None = None) -> tuple[list[CurvePoint], FitConfig, float]:
    """Fit ``data`` with the ``cpu`` preset (+ ``overrides``); the curve, the config and the fit seconds."""
    cfg = resolve_config("cpu", [f"threads={threads}", *(overrides or [])])
    set_threads(cfg.threads)
    session = prepare_fit(cfg, data)
    trainer = session.trainer
    views = cast_test_views(load_scene(data, "test"), session.geometry)
    points = positions(views)

    def scores() -> dict[str, float]:
        mat = material_at(session.model, *points)
        return material_scores(views, split_views(views, mat.albedo.cpu().numpy()),
                               split_views(views, mat.roughness.cpu().numpy()))

    steps = session.config.steps if max_steps is None else min(session.config.steps, max_steps)
    curve, fit_s = [CurvePoint(0, 0.0, scores())], 0.0
    while trainer.step < steps:
        t0 = time.perf_counter()
        trainer.train_step()
        fit_s += time.perf_counter() - t0
        if trainer.step % every == 0 or trainer.step == steps:
            curve.append(CurvePoint(trainer.step, fit_s, scores()))
    return curve, session.config, fit_s


def write_curve_csv(path: Path, points: list[CurvePoint]) -> None:
    keys = list(points[0].scores) if points else []
    lines = ["step,fit_s," + ",".join(keys)]
    for p in points:
        vals = ["" if p.scores[k] is None else f"{p.scores[k]:.6g}" for k in keys]
        lines.append(f"{p.step},{p.fit_s:.3f}," + ",".join(vals))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def read_curve_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns by name (empty cells are NaN)."""
    rows = [ln.split(",") for ln in path.read_text().splitlines() if ln]
    head, body = rows[0], rows[1:]
    return {k: np.array([float(r[i]) if i < len(r) and r[i] != "" else np.nan for r in body])
            for i, k in enumerate(head)}
