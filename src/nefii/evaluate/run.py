"""The one eval loop: render a fitted run's test views, score them as Table 1 does, write what was measured.

``nefii eval`` calls :func:`evaluate_run`; a benchmark that scores another system's predictions calls
:func:`score_and_write_view` per view and :func:`finish_metrics`, so both are scored and written alike.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch

from ..data.scene import SceneData
from ..fit.outputs import ENVMAP_SIZE, FittedRun
from ..fit.trainer import transport_of
from ..io.atomic import atomic_dir
from ..io.exr import write_exr
from ..io.images import write_png
from .render_views import render_view
from .outputs import tonemap_display, write_grid, write_metrics
from .table1 import ViewArrays, mean_scores, view_scores


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().float().numpy()


def ground_truth(scene: SceneData, v: int) -> ViewArrays:
    """View ``v``'s photo and whatever ground-truth maps the dataset has for it."""
    gt = scene.ground_truth

    def layer(name: str) -> np.ndarray | None:
        maps = None if gt is None else getattr(gt, name)
        return None if maps is None else _np(maps[v])

    return ViewArrays(_np(scene.images[v]), layer("albedo"), layer("roughness"), layer("specular"))


def eval_mask(scene: SceneData, v: int, hit_mask: np.ndarray) -> np.ndarray:
    """The pixels scored in view ``v``: the ground-truth mask, else the dataset's mask, else where the
    geometry is hit."""
    gt = scene.ground_truth
    if gt is not None and gt.mask is not None:
        return _np(gt.mask[v]).astype(bool)
    if scene.masks is not None:
        return _np(scene.masks[v]).astype(bool)
    return hit_mask.astype(bool)


def score_and_write_view(out: Path, index: int, name: str, pred: ViewArrays, truth: ViewArrays, mask: np.ndarray,
                         extra_layers: dict[str, np.ndarray] | None = None) -> dict:
    """Table 1 scores of one view; writes ``K_{rgb,specular,albedo,roughness,...}.exr`` and ``K_grid.png``
    into ``out`` and returns the view's entry of metrics.json."""
    scores, scale = view_scores(pred, truth, mask)
    layers = {"rgb": pred.rgb, "specular": pred.specular, "albedo": pred.albedo, "roughness": pred.roughness,
              **(extra_layers or {})}
    for layer, arr in layers.items():
        if arr is not None:
            write_exr(out / f"{index}_{layer}.exr", arr)
    rows, flags = [(tonemap_display(truth.rgb), tonemap_display(pred.rgb))], [False]
    if truth.albedo is not None:
        rows.append((truth.albedo, pred.albedo * scale))
        flags.append(True)
    if truth.roughness is not None:
        rows.append((truth.roughness, pred.roughness))
        flags.append(False)
    if truth.specular is not None and pred.specular is not None:
        rows.append((tonemap_display(truth.specular), tonemap_display(pred.specular)))
        flags.append(False)
    write_grid(out / f"{index}_grid.png", rows, flags)
    return {"index": index, "name": name, "albedo_scale": [float(s) for s in scale], **scores}


def finish_metrics(out: Path, views: list[dict], notes: dict[str, str]) -> dict[str, dict]:
    """Means over views (both protocols), written as ``metrics.json`` and ``metrics.md``; returns the means."""
    means = mean_scores(views)
    write_metrics(out, means, views, notes)
    return means


@torch.no_grad()
def evaluate_run(fitted: FittedRun, scene: SceneData, out: Path, spp: int, generator: torch.Generator | None,
                 progress: Callable[[Iterable[int]], Iterable[int]] = lambda it: it) -> dict[str, dict]:
    """Render every view of ``scene`` (a test split) with ``fitted``'s model and the estimator it was trained
    with, score it, and write ``out`` (metrics.json/md, per-view EXRs and grids, the recovered environment
    beside the true one) atomically. Returns the mean scores per protocol."""
    geometry = fitted.open_geometry()
    transport = transport_of(fitted.config)
    views = []
    with atomic_dir(out) as tmp:
        for v in progress(range(len(scene))):
            pred = render_view(fitted.model, geometry, scene.cameras, v, spp, generator, transport)
            p = ViewArrays(_np(pred.rgb), _np(pred.albedo), _np(pred.roughness), _np(pred.specular))
            mask = eval_mask(scene, v, _np(pred.mask))
            views.append(score_and_write_view(tmp, scene.indices[v], scene.names[v], p, ground_truth(scene, v), mask,
                                              {"normal": _np(pred.normal), "cache": _np(pred.cache)}))
        rec = _np(fitted.model.env.to_equirect(*ENVMAP_SIZE))
        env_rows = [tonemap_display(rec)]
        if scene.envmap is not None:
            env_rows.insert(0, tonemap_display(_resize(_np(scene.envmap), ENVMAP_SIZE)))
        write_png(tmp / "envmap_gt_vs_recovered.png", np.concatenate(env_rows, 0))
        notes = {"albedo": "aligned per view and channel by median(gt/pred) over the mask, linear; scored in sRGB",
                 "spp": f"{spp} estimator samples per pixel (x3 directions)",
                 "views": f"{len(views)} test views from {scene.root}"}
        return finish_metrics(tmp, views, notes)


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of an (H, W, 3) map to ``size`` = (H', W'), to show side by side."""
    h, w = img.shape[:2]
    rows = (np.arange(size[0]) * h // size[0]).clip(0, h - 1)
    cols = (np.arange(size[1]) * w // size[1]).clip(0, w - 1)
    return img[rows][:, cols]
