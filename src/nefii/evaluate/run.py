"""The one eval loop: render a fitted run's test views, score them as Table 1 does, write what was measured.

``nefii eval`` calls :func:`evaluate_run`; a benchmark that scores another system's predictions calls
:func:`score_and_write_view` per view and :func:`finish_metrics`, so both are scored and written alike.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch
from torch import nn

from ..data.fingerprint import fingerprint
from ..data.scene import SceneData
from ..fit.outputs import ENVMAP_SIZE, FittedRun
from ..fit.trainer import transport_of
from ..io.exr import write_exr
from ..io.images import write_png
from .partial import PartialViews, model_sha256, view_seed
from .render_views import render_view
from .outputs import tonemap_display, write_grid, write_metrics
from .table1 import ViewArrays, mean_scores, view_scores


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().float().numpy()


def _np_or_none(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else _np(t)


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
    rows: list[tuple[np.ndarray, np.ndarray]] = []
    flags: list[bool] = []
    if pred.rgb is not None:
        rows.append((tonemap_display(truth.rgb), tonemap_display(pred.rgb)))
        flags.append(False)
    if truth.albedo is not None:
        rows.append((truth.albedo, pred.albedo * scale))
        flags.append(True)
    if truth.roughness is not None:
        rows.append((truth.roughness, pred.roughness))
        flags.append(False)
    if truth.specular is not None and pred.specular is not None:
        rows.append((tonemap_display(truth.specular), tonemap_display(pred.specular)))
        flags.append(False)
    if rows:
        write_grid(out / f"{index}_grid.png", rows, flags)
    return {"index": index, "name": name, "albedo_scale": [float(s) for s in scale], **scores}


def finish_metrics(out: Path, views: list[dict], notes: dict[str, str]) -> dict[str, dict]:
    """Means over views (both protocols), written as ``metrics.json`` and ``metrics.md``; returns the means."""
    means = mean_scores(views)
    write_metrics(out, means, views, notes)
    return means


@dataclass(frozen=True)
class EvalKey:
    """What an eval's per-view results depend on."""

    model: str
    """sha256 of the model's parameters and buffers"""
    cameras: str
    """sha256 of the test views' poses, intrinsics and size"""
    images: str
    """sha256 of the test images as loaded (after any downscale)"""
    views: tuple[int, ...]
    """the test views' indices scored"""
    spp: int
    seed: int
    device: str
    """``cpu`` or ``cuda``: their floating point differs"""

    @staticmethod
    def of(model: nn.Module, scene: SceneData, views: list[int], spp: int, seed: int, device: str) -> "EvalKey":
        data = fingerprint(scene, None)
        return EvalKey(model_sha256(model), data.cameras, data.images, tuple(views), spp, seed, device)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


def spread_views(count: int, limit: int) -> list[int]:
    """``limit`` of ``count`` views spread evenly from the first to the last (all of them when ``limit`` is 0
    or not below ``count``)."""
    if limit <= 0 or limit >= count:
        return list(range(count))
    return sorted(set(np.linspace(0, count - 1, limit).round().astype(int).tolist()))


@torch.no_grad()
def evaluate_run(fitted: FittedRun, scene: SceneData, out: Path, spp: int, seed: int, max_views: int = 0,
                 progress: Callable[[Iterable[int]], Iterable[int]] = lambda it: it,
                 say: Callable[[str], None] = lambda line: None) -> dict[str, dict]:
    """Render the views of ``scene`` (a test split; ``max_views`` of them spread evenly, 0: all) with
    ``fitted``'s model and the estimator it was trained with, score them, and write ``out`` (metrics.json/md,
    per-view EXRs and grids, the recovered environment beside the true one) as a whole. ``spp = 0`` scores the
    material only (albedo and roughness against the dataset's maps, which it must have): no colour is
    path-traced, and the specular and RGB columns are empty. Each view is committed
    as it is scored (:mod:`nefii.evaluate.partial`): a rerun after an interruption scores only the views left,
    and writes what an uninterrupted eval writes. Returns the mean scores per protocol."""
    geometry = fitted.open_geometry()
    transport = transport_of(fitted.config)
    device = next(fitted.model.parameters()).device
    chosen = spread_views(len(scene), max_views)
    partial = PartialViews(out, EvalKey.of(fitted.model, scene, [scene.indices[v] for v in chosen],
                                           spp, seed, device.type).to_json())
    done = {v: partial.done(scene.indices[v]) for v in chosen}
    resumed = sum(e is not None for e in done.values())
    if resumed:
        say(f"nefii eval: {resumed} of {len(chosen)} views already scored by an interrupted eval "
            f"({partial.folder}); scoring the rest")
    tmp = partial.folder
    for v in progress([v for v in chosen if done[v] is None]):
        index = scene.indices[v]
        g = torch.Generator(device=device).manual_seed(view_seed(seed, index))
        pred = render_view(fitted.model, geometry, scene.cameras, v, spp, g, transport)
        p = ViewArrays(_np_or_none(pred.rgb), _np(pred.albedo), _np(pred.roughness), _np_or_none(pred.specular))
        mask = eval_mask(scene, v, _np(pred.mask))
        done[v] = score_and_write_view(tmp, index, scene.names[v], p, ground_truth(scene, v), mask,
                                       {"normal": _np(pred.normal), "cache": _np(pred.cache)})
        partial.commit(index, done[v])
    rec = _np(fitted.model.env.to_equirect(*ENVMAP_SIZE))
    env_rows = [tonemap_display(rec)]
    if scene.envmap is not None:
        env_rows.insert(0, tonemap_display(_resize(_np(scene.envmap), ENVMAP_SIZE)))
    write_png(tmp / "envmap_gt_vs_recovered.png", np.concatenate(env_rows, 0))
    shown = f"{len(chosen)} test views" if len(chosen) == len(scene) else \
        f"{len(chosen)} of {len(scene)} test views, spread evenly (--max-views)"
    notes = {"albedo": "aligned per view and channel by median(gt/pred) over the mask, linear; scored in sRGB",
             "spp": (f"{spp} estimator samples per pixel (x3 directions)" if spp > 0 else
                     "material only (--material-only): no colour path-traced, specular and RGB not scored"),
             "views": f"{shown} from {scene.root}"}
    means = finish_metrics(tmp, [done[v] for v in chosen], notes)
    partial.finish()
    return means


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of an (H, W, 3) map to ``size`` = (H', W'), to show side by side."""
    h, w = img.shape[:2]
    rows = (np.arange(size[0]) * h // size[0]).clip(0, h - 1)
    cols = (np.arange(size[1]) * w // size[1]).clip(0, w - 1)
    return img[rows][:, cols]
