"""``nefii fit DATA --out RUN``: the NeFII joint optimisation on frozen geometry."""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import torch

from ..errors import InputError
from ..fit.config import PRESETS, FitConfig, resolve_config
from ..fit.distributed import DistContext, init_distributed, local_device, parameter_checksums, shutdown
from ..fit.logging import RunLogger
from ..fit.outputs import read_config, write_config, write_exposure, write_outputs
from ..fit.preview import write_preview
from ..fit.session import prepare_fit
from ..fit.trainer import NonFiniteLoss
from ..io.atomic import write_text_atomic
from ..io.checkpoints import load_latest_checkpoint
from ..run_folder import (MANIFEST_FILE, RunManifest, after_failure, has_progress, read_manifest, resume_point,
                          write_manifest, writing_run)
from .common import pick_device, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="recover materials, SG lighting and the radiance cache", description=__doc__)
    p.add_argument("data", type=Path, help="dataset folder (any format nefii reads)")
    p.add_argument("--out", type=Path, required=True, help="run folder to write")
    p.add_argument("--preset", default="cpu", choices=sorted(PRESETS), help="starting configuration")
    p.add_argument("--mesh", type=Path, default=None, help="frozen geometry (default: the scene's mesh.ply; a dataset without one "
                        "is reconstructed from its images first, by nefii geometry into RUN/geometry)")
    p.add_argument("--geometry", type=Path, default=None, metavar="GEO",
                   help="the output of nefii geometry instead of a mesh; --set geometry_mode=mesh|sdf says how to use it")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out")
    p.add_argument("--device", default="auto", help="cpu | cuda | cuda:N | auto")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set steps=500 --set material.hidden=128")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def fit_config(args: argparse.Namespace) -> FitConfig:
    try:
        cfg = resolve_config(args.preset, args.overrides)
    except (KeyError, ValueError) as e:
        raise InputError(None, f"bad configuration: {e.args[0] if e.args else e}") from None
    return cfg


def resumed_config(args: argparse.Namespace, cfg: FitConfig) -> FitConfig:
    """On ``--resume``, the run's own ``config.json`` (once the folder is known to be a fit run)."""
    if not args.resume or not (args.out / "config.json").is_file():
        return cfg
    saved = read_config(args.out)
    if args.overrides or args.preset != saved.preset:
        print("nefii fit: --resume continues with the run's own config.json; --preset/--set are ignored")
    return saved


def run(args: argparse.Namespace) -> int:
    cfg = fit_config(args)
    device = pick_device(args.device)
    ctx = init_distributed(device)
    clean = False
    try:
        if not ctx.is_main:                 # rank 0 alone holds the folder and writes it
            rc = _fit(args, cfg, ctx, None)
        else:
            with writing_run(args.out, "fit", args.resume, warn=_warn) as manifest:
                rc = _fit(args, cfg, ctx, manifest)
        clean = True
        return rc
    finally:
        shutdown(ctx, clean)


def _warn(line: str) -> None:
    print(f"nefii fit: warning: {line}", file=sys.stderr)


GEOMETRY_FOLDER = "geometry"
"""where ``nefii fit`` puts the geometry it reconstructs for a dataset without a mesh: ``RUN/geometry``"""


class GeometryStageFailed(Exception):
    """The geometry stage that ``nefii fit`` ran for a dataset without a mesh stopped on an error (it said which)."""


def _stage_overrides(cfg: FitConfig) -> list[str]:
    """The fit's settings its geometry stage shares: the seed (a second seed of the one command is a second
    reconstruction too), the threads, and a gain per view (the same photos)."""
    return [f"seed={cfg.seed}"] + ([f"threads={cfg.threads}"] if cfg.threads else []) + (
        ["exposure=per_view"] if cfg.exposure == "per_view" else [])


def _reconstruct(args: argparse.Namespace, cfg: FitConfig, ctx: DistContext) -> Path:
    """The dataset has no mesh and none was given: ``nefii geometry`` into ``RUN/geometry`` (its own run folder:
    resumed where a stopped fit left it, reused once it is done), the geometry preset named as the fit's, with
    the fit's seed, threads and per-view gains (the fit's other settings are the fit's own)."""
    from . import geometry as geometry_cli
    from ..sdf.config import GEOMETRY_PRESETS
    from ..sdf.outputs import MESH_FILE, SDF_FILE
    geo = args.out / GEOMETRY_FOLDER
    if ctx.active:
        raise InputError(args.data, "has no mesh: with several processes, run nefii geometry first and pass "
                                    "--geometry GEO")
    if (geo / SDF_FILE).is_file() and (geo / MESH_FILE).is_file():
        print(f"nefii fit: the dataset has no mesh: using the geometry reconstructed from its images in {geo}")
        return geo
    fresh = read_manifest(args.out) is None
    if fresh:                                # from here the folder holds a fit run, even before its first step
        args.out.mkdir(parents=True, exist_ok=True)
        write_manifest(args.out, RunManifest("fit", None))
    preset = cfg.preset if cfg.preset in GEOMETRY_PRESETS else "cpu"
    print(f"nefii fit: the dataset has no mesh: reconstructing the object from its images first (nefii geometry, "
          f"preset {preset}, into {geo}; --mesh or --geometry skips this)")
    stage = argparse.Namespace(data=args.data, out=geo, preset=preset, masks="auto", from_mesh=None,
                               resume=geo.is_dir() and has_progress(geo, "geometry"), device=args.device,
                               overrides=_stage_overrides(cfg), quiet=args.quiet)
    try:
        rc = geometry_cli.run(stage)
    except InputError:
        if fresh:
            (args.out / MANIFEST_FILE).unlink(missing_ok=True)
        raise
    if rc != 0:
        raise GeometryStageFailed
    return geo


def _fit(args: argparse.Namespace, cfg: FitConfig, ctx: DistContext, manifest: RunManifest | None) -> int:
    out: Path = args.out
    started = time.time()
    cfg = resumed_config(args, cfg)
    device = local_device(pick_device(args.device), ctx)
    threads = set_threads(cfg.threads)
    say = print if ctx.is_main else (lambda *a, **k: None)
    checkpoint = None
    if args.resume:
        if ctx.is_main:
            checkpoint = resume_point(out, "fit", manifest, _warn, lambda line: print(f"nefii fit: {line}"))
        else:   # the other ranks read the same file rank 0 chose
            checkpoint = load_latest_checkpoint(out / "checkpoints")
    recorded = None if manifest is None or manifest.data is None or checkpoint is None else (out, manifest.data)
    say(f"nefii fit: device {device}, {threads} threads" + (f", {ctx.world_size} processes" if ctx.active else ""))
    if cfg.preset == "gpu" and device.type == "cpu" and ctx.is_main:
        _warn("the gpu preset on the CPU takes about 16 times the cpu preset's samples a step (use --device cuda, or "
              "--preset cpu)")
    try:
        session = prepare_fit(cfg, args.data, mesh=args.mesh, geometry_dir=args.geometry, device=device, dist=ctx,
                              checkpoint=checkpoint, resume_of=recorded, say=lambda line: say(f"nefii fit: {line}"),
                              reconstruct=lambda: _reconstruct(args, cfg, ctx))
    except GeometryStageFailed:
        return 1
    cfg, trainer, ckpt_dir = session.config, session.trainer, out / "checkpoints"
    logger = None
    if ctx.is_main:
        out.mkdir(parents=True, exist_ok=True)
        write_manifest(out, RunManifest("fit", session.data))
        ckpt_dir.mkdir(exist_ok=True)
        write_config(out, cfg)
        if checkpoint is None:              # a fresh start: the log of a run that failed before is not this one's
            (out / "log.csv").unlink(missing_ok=True)
        logger = RunLogger(out, cfg)
    t0, step0 = time.time(), trainer.step

    def preview(step: int) -> None:
        write_preview(out / "previews" / f"step_{step:07d}.png", trainer.model, session.geometry, session.scene,
                      view=(step // max(cfg.preview_every, 1)) % len(session.scene), transport=trainer.transport,
                      radiance_unit=session.radiance_unit)

    try:
        trainer.fit(ckpt_dir, log=logger, progress=not args.quiet, preview=preview)
    except NonFiniteLoss as e:
        say(f"nefii fit: error: {e}; {after_failure(out)}")
        return 1
    finally:
        if logger is not None:
            logger.close()
    if ctx.active:
        sums = parameter_checksums(trainer.model, ctx, device)
        if max(sums) - min(sums) > 1e-6 * max(1.0, abs(sums[0])):
            say(f"nefii fit: error: the {ctx.world_size} replicas diverged (parameter sums {sums})")
            return 1
        say(f"nefii fit: the {ctx.world_size} process replicas are in sync (parameter sum {sums[0]:.6g})")
    if ctx.is_main:
        write_outputs(out, cfg, trainer.model, session.box, Path(args.data).resolve(), session.source,
                      session.radiance_unit)
        if trainer.gains is not None:
            write_exposure(out, session.scene.names, trainer.gains.all())
        wall = time.time() - t0
        stats = {"steps": trainer.step, "steps_this_session": trainer.step - step0, "wall_s_this_session": wall,
                 "steps_per_s": (trainer.step - step0) / max(wall, 1e-9), "processes": ctx.world_size,
                 "threads": threads, "device": str(device),
                 "setup_s": t0 - started, "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
        if device.type == "cuda":
            stats["peak_gpu_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
        write_text_atomic(out / "fit_stats.json", json.dumps(stats, indent=2) + "\n")
        written = [n for n in ("model.pt", "envmap.exr", "sg.npy", "config.json", "fit_stats.json")
                   if (out / n).exists()]
        say(f"nefii fit: done, {trainer.step} steps; wrote {', '.join(written)} in {out}")
    return 0
