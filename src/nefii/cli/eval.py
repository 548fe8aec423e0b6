"""``nefii eval RUN``: render every test view and score it as the paper's Table 1 does."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..data import load_scene
from ..evaluate.render_views import render_view
from ..evaluate.report import tonemap_display, write_grid, write_metrics
from ..evaluate.table1 import ViewArrays, mean_scores, view_scores
from ..fit.model import Transport
from ..fit.outputs import ENVMAP_SIZE, load_run
from ..io.atomic import atomic_dir
from ..io.exr import write_exr
from ..io.images import write_png
from .common import pick_device, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="render the test views and compute the Table 1 metrics", description=__doc__)
    p.add_argument("run", type=Path, help="run folder written by `nefii fit`")
    p.add_argument("--data", type=Path, default=None, help="dataset with the test split (default: the fitted one)")
    p.add_argument("--spp", type=int, default=256,
                   help="estimator samples per pixel; each draws one cosine, one GGX and one SG direction")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().float().numpy()


def run(args: argparse.Namespace) -> int:
    device = pick_device(args.device)
    fitted = load_run(args.run, device)
    set_threads(fitted.config.threads)
    scene = load_scene(args.data or fitted.data, "test")
    geometry = fitted.open_geometry()
    gt = scene.ground_truth
    transport = Transport(indirect=fitted.config.indirect, visibility=fitted.config.visibility)
    g = torch.Generator(device=device).manual_seed(args.seed)
    views = []
    with atomic_dir(args.run / "eval") as out:
        for v in tqdm(range(len(scene)), desc="eval", unit="view", disable=args.quiet):
            pred = render_view(fitted.model, geometry, scene.cameras, v, args.spp, g, transport)
            k = scene.indices[v]
            if gt is not None and gt.mask is not None:
                mask = _np(gt.mask[v]).astype(bool)
            elif scene.masks is not None:
                mask = _np(scene.masks[v]).astype(bool)
            else:
                mask = _np(pred.mask).astype(bool)
            p = ViewArrays(_np(pred.rgb), _np(pred.albedo), _np(pred.roughness), _np(pred.specular))
            t = ViewArrays(_np(scene.images[v]),
                           None if gt is None or gt.albedo is None else _np(gt.albedo[v]),
                           None if gt is None or gt.roughness is None else _np(gt.roughness[v]),
                           None if gt is None or gt.specular is None else _np(gt.specular[v]))
            scores, scale = view_scores(p, t, mask)
            views.append({"index": k, "name": scene.names[v], "albedo_scale": [float(s) for s in scale], **scores})
            for name, arr in (("rgb", p.rgb), ("specular", p.specular), ("albedo", p.albedo),
                              ("roughness", p.roughness), ("normal", _np(pred.normal)), ("cache", _np(pred.cache))):
                write_exr(out / f"{k}_{name}.exr", arr)
            rows = [(tonemap_display(t.rgb), tonemap_display(p.rgb))]
            flags = [False]
            if t.albedo is not None:
                rows.append((t.albedo, p.albedo * scale))
                flags.append(True)
            if t.roughness is not None:
                rows.append((t.roughness, p.roughness))
                flags.append(False)
            if t.specular is not None:
                rows.append((tonemap_display(t.specular), tonemap_display(p.specular)))
                flags.append(False)
            write_grid(out / f"{k}_grid.png", rows, flags)
        with torch.no_grad():
            rec = _np(fitted.model.env.to_equirect(*ENVMAP_SIZE))
        env_rows = [tonemap_display(rec)]
        if scene.envmap is not None:
            gt_env = _resize(_np(scene.envmap), ENVMAP_SIZE)
            env_rows.insert(0, tonemap_display(gt_env))
        write_png(out / "envmap_gt_vs_recovered.png", np.concatenate(env_rows, 0))
        means = mean_scores(views)
        notes = {"albedo": "aligned per view and channel by median(gt/pred) over the mask, linear; scored in sRGB",
                 "spp": f"{args.spp} estimator samples per pixel (x3 directions)",
                 "views": f"{len(views)} test views from {scene.root}"}
        write_metrics(out, means, views, notes)
    print((args.run / "eval" / "metrics.md").read_text())
    print(f"nefii eval: per-view EXRs and GT | ours | error grids in {args.run / 'eval'}")
    return 0


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of an (H, W, 3) map to ``size`` = (H', W'), to show side by side."""
    h, w = img.shape[:2]
    rows = (np.arange(size[0]) * h // size[0]).clip(0, h - 1)
    cols = (np.arange(size[1]) * w // size[1]).clip(0, w - 1)
    return img[rows][:, cols]
