"""``nefii refine RUN``: the geometry of a fit on a reconstruction refined through the physically based fit.

RUN is a finished ``nefii fit DATA --geometry GEO --out RUN``. Its SDF is optimised with its material, light
and cache (:mod:`nefii.fit.refine`); the refined SDF and mesh are written to ``RUN/refined/`` and ``RUN/model.pt``
is rewritten to use them (the fit's own is kept as ``RUN/model_unrefined.pt``), so ``nefii eval``, ``relight``,
``export`` and ``view`` of RUN use the refined surface.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import shutil
import time
from pathlib import Path

import torch
from tqdm import tqdm

from ..config_tools import apply_overrides, dataclass_from_dict
from ..data import load_scene
from ..data.downscale import training_images
from ..errors import InputError
from ..fit.outputs import load_run, write_outputs
from ..fit.refine import RefineConfig, Refiner, TrainingRays
from ..io.atomic import atomic_path, write_text_atomic
from ..io.checkpoints import load_latest_checkpoint, save_checkpoint
from ..sdf.outputs import MESH_FILE, load_sdf, save_sdf
from .common import set_threads

REFINED, UNREFINED = "refined", "model_unrefined.pt"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("refine", help="refine a reconstruction's geometry through the fit", description=__doc__)
    p.add_argument("run", type=Path, help="run folder of nefii fit --geometry GEO")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in RUN/refined")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a refinement setting, e.g. --set steps=400 (see nefii.fit.refine.RefineConfig)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def refine_config(overrides: list[str]) -> RefineConfig:
    values = dataclasses.asdict(RefineConfig())
    try:
        apply_overrides(values, overrides)
        return dataclass_from_dict(RefineConfig, values)
    except (KeyError, ValueError) as e:
        raise InputError(None, f"bad refinement setting: {e.args[0] if e.args else e}") from None


def run(args: argparse.Namespace) -> int:
    cfg = refine_config(args.overrides)
    folder: Path = args.run
    out = folder / REFINED
    if (out / "sdf.pt").is_file():
        raise InputError(out, f"already refined (to refine the fit again, remove this folder and put {UNREFINED} "
                              "back as model.pt)")
    fitted = load_run(folder)
    source = fitted.geometry
    if source.folder is None:
        raise InputError(folder, f"the run's geometry is the mesh {source.mesh}, not the output of nefii geometry: "
                                 "refine needs a fit made with --geometry GEO")
    if source.mode != "mesh":
        raise InputError(folder, "refine works on fits with geometry_mode=mesh (the run used sdf)")
    threads = set_threads(cfg.threads)
    device = torch.device("cpu")
    loaded = load_sdf(source.folder)
    scene, line = training_images(load_scene(fitted.data, "train"), fitted.config.max_image_side)
    rays = TrainingRays.of(scene)
    model = fitted.model.train()
    g = loaded.config
    refiner = Refiner(cfg, fitted.config, model, loaded.sdf, loaded.normalization, rays, source.normal_sigma,
                      source.lookup_sigma, (g.lr * g.lr_decay, g.lr_networks * g.lr_decay), device)
    ckpt_dir = out / "checkpoints"
    if args.resume:
        ckpt = load_latest_checkpoint(ckpt_dir, warn=lambda s: print(f"nefii refine: warning: {s}"))
        if ckpt is not None:
            ckpt.restore(refiner.load_state_dict, "this refinement")
            print(f"nefii refine: resumed from {ckpt.path} at step {refiner.step}")
    print("nefii refine: warning: experimental; on the built-in scenes it has so far opened holes and cost the "
          "materials several dB (benchmarks/results/geometry.md); the fit's own model stays in model_unrefined.pt")
    print(f"nefii refine: {threads} threads; {len(scene)} views {scene.width}x{scene.height} from {scene.root}"
          + (f" ({line})" if line else "") + f"; the SDF of {source.folder}"
          + ("" if scene.masks is not None else "; no masks: the silhouette term is off"))
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    t0, step0, last = time.time(), refiner.step, time.monotonic()
    sums = {"silhouette": 0.0, "eikonal": 0.0, "image": 0.0, "hits": 0.0}
    bar = tqdm(total=cfg.steps, initial=refiner.step, disable=args.quiet, desc="refine", unit="step")
    while refiner.step < cfg.steps:
        try:
            terms = refiner.train_step()
        except FloatingPointError as e:
            bar.close()
            print(f"nefii refine: error: {e}; the run's model.pt is untouched"
                  + (f", checkpoints in {ckpt_dir}" if any(ckpt_dir.iterdir()) else ""))
            return 1
        sums["silhouette"] += terms.silhouette.item()
        sums["eikonal"] += terms.eikonal.item()
        sums["image"] += 0.0 if terms.image is None else terms.image.total.item()
        sums["hits"] += terms.hits
        bar.update(1)
        if time.monotonic() - last >= cfg.checkpoint_every_s and refiner.step < cfg.steps:
            save_checkpoint(ckpt_dir, refiner.step, refiner.state_dict())
            last = time.monotonic()
    bar.close()
    mesh = refiner.zero_set(cfg.mesh_resolution)
    save_sdf(out, loaded.config, refiner.sdf, loaded.normalization, f"refined from {source.folder} by nefii refine")
    with atomic_path(out / MESH_FILE) as tmp:
        mesh.export(tmp, file_type="ply")
    if not (folder / UNREFINED).is_file():
        shutil.copy2(folder / "model.pt", folder / UNREFINED)
    refined = dataclasses.replace(source, mesh=(out / MESH_FILE).resolve(), folder=out.resolve())
    write_outputs(folder, fitted.config, model.eval(), fitted.box, fitted.data, refined)
    n = max(refiner.step - step0, 1)
    wall = time.time() - t0
    stats = {"steps": refiner.step, "steps_this_session": refiner.step - step0, "wall_s_this_session": wall,
             "mean_losses_this_session": {k: v / n for k, v in sums.items()}, "config": dataclasses.asdict(cfg),
             "from": str(source.folder), "threads": threads,
             "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
    write_text_atomic(out / "refine_stats.json", json.dumps(stats, indent=2) + "\n")
    print(f"nefii refine: done, {refiner.step} steps in {wall / 60:.1f} min; wrote {out / 'sdf.pt'}, "
          f"{out / MESH_FILE} ({len(mesh.faces)} triangles) and {folder / 'model.pt'} (the fit's own: {UNREFINED})")
    return 0

