"""``nefii refine RUN``: the geometry of a fit on a reconstruction refined through the physically based fit.

RUN is a finished ``nefii fit DATA --geometry GEO --out RUN``. Two phases: its SDF is optimised with its
material, light and cache (:mod:`nefii.fit.refine`) and written with its mesh to ``RUN/refined/``; then the
materials, light and cache are fitted again from the start on that mesh with the run's own settings, and
``RUN/model.pt`` is rewritten with them (the fit's own is kept as ``RUN/model_unrefined.pt``), so ``nefii eval``,
``relight``, ``export`` and ``view`` of RUN use the refined surface. ``--resume`` continues either phase.
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
from ..data.scene import SceneData
from ..errors import InputError
from ..fit.outputs import FittedRun, load_run, write_outputs
from ..fit.session import prepare_fit
from ..fit.trainer import NonFiniteLoss
from ..fit.refine import GeometryAnchor, RefineConfig, Refiner, TrainingRays
from ..io.atomic import atomic_path, write_text_atomic
from ..io.checkpoints import load_latest_checkpoint, save_checkpoint
from ..io.lock import RunLock
from ..sdf.model import NeuSModel
from ..sdf.outputs import MESH_FILE, LoadedSDF, load_sdf, save_sdf
from ..sdf.train import ImageObjective
from .common import set_threads

REFINED, UNREFINED, STATS = "refined", "model_unrefined.pt", "refine_stats.json"
GEOMETRY_PHASE = "geometry_phase.json"
"""the first phase's record, kept for the final stats when the second phase is resumed"""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("refine", help="refine a reconstruction's geometry through the fit", description=__doc__)
    p.add_argument("run", type=Path, help="run folder of nefii fit --geometry GEO")
    p.add_argument("--resume", action="store_true",
                   help="continue from the last checkpoint in RUN/refined (either phase)")
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


def geometry_anchor(folder: Path, loaded: LoadedSDF, scene: SceneData) -> GeometryAnchor | None:
    """The geometry stage's objective on the model it ended with (``GEO/checkpoints``' last, whose SDF is
    ``GEO/sdf.pt``'s), on ``scene``'s images (with its masks if the stage used masks); None when the stage fitted
    the SDF to a mesh (no colour network to keep)."""
    stats = folder / "geometry_stats.json"
    try:
        record = json.loads(stats.read_text())
        source = str(record["source"])
        unit = float(record.get("radiance_unit", 1.0))      # a stage from before the unit took colours as they were
    except (OSError, ValueError, KeyError) as e:
        raise InputError(stats, f"cannot read the geometry stage's record ({type(e).__name__}: {e})") from None
    if not source.startswith("images"):
        return None
    ckpt = load_latest_checkpoint(folder / "checkpoints")
    cfg = loaded.config
    if ckpt is None or ckpt.step != cfg.steps:
        raise InputError(folder / "checkpoints", f"no checkpoint of the geometry stage's last step ({cfg.steps}): "
                                                 "refine keeps that stage's objective and needs its colour network")
    masks = scene.masks if "with masks" in source else None
    model = NeuSModel(cfg, background=masks is None, num_views=len(scene))
    ckpt.restore(lambda state: model.load_state_dict(state["model"]), "the geometry stage's model")
    model.sdf.load_state_dict(loaded.sdf.state_dict())
    return GeometryAnchor(model, ImageObjective.from_views(cfg, scene, loaded.normalization, masks, torch.device("cpu"),
                                                           unit),
                          cfg.steps)


def run(args: argparse.Namespace) -> int:
    cfg = refine_config(args.overrides)
    folder: Path = args.run
    if not (folder / "model.pt").is_file():
        raise InputError(folder / "model.pt", "not found: has `nefii fit` finished in this folder?")
    lock = RunLock(folder, "refine")            # one writer at a time: fit and geometry hold the same lock
    lock.acquire(warn=lambda line: print(f"nefii refine: warning: {line}"))
    try:
        return _run(args, cfg, folder)
    finally:
        lock.release()


def _run(args: argparse.Namespace, cfg: RefineConfig, folder: Path) -> int:
    out = folder / REFINED
    if (out / STATS).is_file():
        raise InputError(out, f"already refined (to refine the fit again, remove this folder and put {UNREFINED} "
                              "back as model.pt)")
    if (out / "sdf.pt").is_file() and not args.resume:
        raise InputError(out, "the geometry is refined but the materials' fit on it did not finish: add --resume")
    fitted = load_run(folder)
    source = fitted.geometry
    if source.folder is None:
        raise InputError(folder, f"the run's geometry is the mesh {source.mesh}, not the output of nefii geometry: "
                                 "refine needs a fit made with --geometry GEO")
    if source.mode != "mesh":
        raise InputError(folder, "refine works on fits with geometry_mode=mesh (the run used sdf)")
    threads = set_threads(cfg.threads)
    print("nefii refine: warning: experimental; on the built-in scenes it has so far moved the surfaces little "
          "(benchmarks/results/geometry.md); the fit's own model stays in model_unrefined.pt")
    t0 = time.time()
    if not (out / "sdf.pt").is_file():
        if not _refine_geometry(args, cfg, fitted, out, threads):
            return 1
    try:
        geometry_stats = json.loads((out / GEOMETRY_PHASE).read_text())
    except (OSError, ValueError) as e:
        raise InputError(out / GEOMETRY_PHASE, f"cannot read the geometry phase's record ({type(e).__name__}: {e}); "
                                               "remove the folder and refine again") from None
    fit_wall = time.time()
    if not _refit(args, fitted, out):
        return 1
    stats = {**geometry_stats,
             "materials_wall_s_this_session": time.time() - fit_wall, "config": dataclasses.asdict(cfg),
             "from": str(source.folder), "threads": threads,
             "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
    write_text_atomic(out / STATS, json.dumps(stats, indent=2) + "\n")
    print(f"nefii refine: done in {(time.time() - t0) / 60:.1f} min; wrote {out / 'sdf.pt'}, {out / MESH_FILE} and "
          f"{folder / 'model.pt'} (the fit's own: {UNREFINED})")
    return 0


def _refine_geometry(args: argparse.Namespace, cfg: RefineConfig, fitted: FittedRun, out: Path,
                     threads: int) -> bool:
    """The SDF refined with the run's material, light and cache; ``out`` gets the refined mesh, the phase's record
    and then the refined SDF (whose presence marks the phase done). False after a failure (said)."""
    source = fitted.geometry
    assert source.folder is not None
    device = torch.device("cpu")
    loaded = load_sdf(source.folder)
    scene, line = training_images(load_scene(fitted.data, "train"), fitted.config.max_image_side)
    rays = TrainingRays.of(scene)
    model = fitted.model.train()
    g = loaded.config
    anchor = geometry_anchor(source.folder, loaded, scene)
    refiner = Refiner(cfg, fitted.config, model, loaded.sdf if anchor is None else anchor.model.sdf,
                      loaded.normalization, rays, source.normal_sigma, source.lookup_sigma,
                      (g.lr * g.lr_decay, g.lr_networks * g.lr_decay), device, anchor)
    ckpt_dir = out / "checkpoints"
    if args.resume:
        ckpt = load_latest_checkpoint(ckpt_dir, warn=lambda s: print(f"nefii refine: warning: {s}"))
        if ckpt is not None:
            ckpt.restore(refiner.load_state_dict, "this refinement")
            print(f"nefii refine: resumed from {ckpt.path} at step {refiner.step}")
    kept = "the geometry stage's objective kept" if anchor is not None else \
        ("silhouette, eikonal and normal priors" if scene.masks is not None else "eikonal and normal priors (no masks)")
    print(f"nefii refine: {threads} threads; {len(scene)} views {scene.width}x{scene.height} from {scene.root}"
          + (f" ({line})" if line else "") + f"; the SDF of {source.folder}, {kept}")
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    t0, step0, last = time.time(), refiner.step, time.monotonic()
    sums = {"anchor": 0.0, "silhouette": 0.0, "eikonal": 0.0, "image": 0.0, "hits": 0.0}
    bar = tqdm(total=cfg.steps, initial=refiner.step, disable=args.quiet, desc="refine", unit="step")
    while refiner.step < cfg.steps:
        try:
            terms = refiner.train_step()
        except FloatingPointError as e:
            bar.close()
            print(f"nefii refine: error: {e}; the run's model.pt is untouched"
                  + (f", checkpoints in {ckpt_dir}" if any(ckpt_dir.iterdir()) else ""))
            return False
        sums["anchor"] += terms.anchor.item()
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
    n = max(refiner.step - step0, 1)
    wall = time.time() - t0
    record = {"steps": refiner.step, "steps_this_session": refiner.step - step0, "wall_s_this_session": wall,
              "mean_losses_this_session": {k: v / n for k, v in sums.items()}}
    with atomic_path(out / MESH_FILE) as tmp:
        mesh.export(tmp, file_type="ply")
    write_text_atomic(out / GEOMETRY_PHASE, json.dumps(record, indent=2) + "\n")
    save_sdf(out, loaded.config, refiner.sdf, loaded.normalization, f"refined from {source.folder} by nefii refine")
    print(f"nefii refine: the geometry refined in {wall / 60:.1f} min ({len(mesh.faces)} triangles); now the "
          "materials are fitted again on it")
    return True


def _refit(args: argparse.Namespace, fitted: FittedRun, out: Path) -> bool:
    """The materials, light and cache fitted again from the start on the refined geometry, with the run's own
    settings (they were trained under the SDF's raw normals during refinement, and every later stage shades with
    the refined mesh's). Writes the run's model.pt (the fit's own kept as model_unrefined.pt)."""
    folder = args.run
    ckpt_dir = out / "fit_checkpoints"
    checkpoint = load_latest_checkpoint(ckpt_dir) if args.resume else None
    session = prepare_fit(fitted.config, fitted.data, geometry_dir=out, checkpoint=checkpoint,
                          say=lambda line: print(f"nefii refine: {line}"))
    ckpt_dir.mkdir(exist_ok=True)
    try:
        session.trainer.fit(ckpt_dir, progress=not args.quiet)
    except NonFiniteLoss as e:
        print(f"nefii refine: error: {e}; the run's model.pt is untouched, checkpoints in {ckpt_dir}")
        return False
    if not (folder / UNREFINED).is_file():
        shutil.copy2(folder / "model.pt", folder / UNREFINED)
    write_outputs(folder, session.config, session.trainer.model, session.box, fitted.data, session.source,
                  session.radiance_unit)
    return True
