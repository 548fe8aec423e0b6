"""nefii's albedo PSNR against fitting time: the ``cpu`` preset's fit, re-run in process with snapshots.

``nefii fit`` keeps no history of its material, so the curve comes from a second run of the same
recipe: the setup of ``nefii.cli.fit`` step for step (``first_hits``, ``build_model``, the
shading-based SG initialisation, ``Trainer``), then ``Trainer.train_step`` until ``cfg.steps``.
Every ``every`` steps the clock stops and the material field is decoded at the test views'
pixel-centre hits (``nefii.fit.outputs.material_at``, the decode ``nefii eval`` uses) and scored
with ``view_scores``. Unlike ``nefii fit`` it writes no checkpoints, previews or logs, so its
steps are a little cheaper than the quality run's; its final point is the same quantity as the
quality run's albedo PSNR (same seed, same code), which the results file shows side by side.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nefii.cli.common import set_threads
from nefii.data import load_scene
from nefii.fit.build import build_model
from nefii.fit.config import FitConfig, resolve_config
from nefii.fit.light_init import estimate_light, set_sg_parameters, sg_from_light
from nefii.fit.outputs import material_at
from nefii.fit.pixels import first_hits
from nefii.fit.trainer import Trainer
from nefii.geometry import MeshGeometry

from views import TestViews, cast_test_views, material_scores, positions, split_views


@dataclass
class CurvePoint:
    step: int
    fit_s: float
    scores: dict[str, float]


def make_trainer(cfg: FitConfig, data: Path) -> tuple[Trainer, MeshGeometry]:
    """What ``nefii fit DATA`` builds before its loop (``nefii.cli.fit._fit``), on the CPU."""
    device = torch.device("cpu")
    scene = load_scene(data, "train")
    geometry = MeshGeometry.from_file(scene.mesh_path)
    box = tuple(torch.from_numpy(b.copy()) for b in geometry.bounds)
    pixels = first_hits(scene, geometry).to(device)
    model = build_model(cfg, box)
    if cfg.light.kind == "sg" and cfg.light.init == "shading":
        pts = pixels.points
        est = estimate_light(pts.position, pts.normal, pts.geometric_normal, pixels.rgb, geometry,
                             generator=torch.Generator().manual_seed(cfg.seed), ray_offset=cfg.ray_offset)
        set_sg_parameters(model.env, sg_from_light(est, cfg.light.num_lobes, sharp=cfg.light.sharpness_init_peak))
    return Trainer(cfg, model, geometry, pixels, device), geometry


def snapshot_scores(trainer: Trainer, views: TestViews, points: tuple[torch.Tensor, torch.Tensor]
                    ) -> dict[str, float]:
    mat = material_at(trainer.model, *points)
    albedo = split_views(views, mat.albedo.cpu().numpy())
    rough = split_views(views, mat.roughness.cpu().numpy())
    return material_scores(views, albedo, rough)


def run_curve(data: Path, threads: int = 1, every: int = 100, overrides: list[str] | None = None,
              max_steps: int | None = None) -> tuple[list[CurvePoint], FitConfig, float]:
    """Fit ``data`` with the ``cpu`` preset (+ ``overrides``); the curve, the config and the fit seconds."""
    cfg = resolve_config("cpu", [f"threads={threads}", *(overrides or [])])
    set_threads(cfg.threads)
    trainer, geometry = make_trainer(cfg, data)
    views = cast_test_views(load_scene(data, "test"), geometry)
    points = positions(views)
    steps = cfg.steps if max_steps is None else min(cfg.steps, max_steps)
    curve = [CurvePoint(0, 0.0, snapshot_scores(trainer, views, points))]
    fit_s = 0.0
    while trainer.step < steps:
        t0 = time.perf_counter()
        trainer.train_step()
        fit_s += time.perf_counter() - t0
        if trainer.step % every == 0 or trainer.step == steps:
            curve.append(CurvePoint(trainer.step, fit_s, snapshot_scores(trainer, views, points)))
    return curve, cfg, fit_s


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
