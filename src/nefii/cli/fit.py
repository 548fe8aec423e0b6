"""``nefii fit DATA --out RUN``: the NeFII joint optimisation on frozen geometry."""
from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import torch

from ..data import load_scene
from ..errors import InputError
from ..fit.build import build_model
from ..fit.config import PRESETS, FitConfig, resolve_config
from ..fit.geometry_source import adapt_to_source, resolve_source
from ..fit.distributed import DistContext, init_distributed, local_device, parameter_checksums, shutdown
from ..fit.light_init import estimate_light, set_sg_parameters, sg_from_light
from ..fit.logging import RunLogger
from ..fit.outputs import read_config, write_config, write_outputs
from ..fit.pixels import first_hits
from ..fit.preview import write_preview
from ..fit.trainer import NonFiniteLoss, Trainer
from ..geometry import MeshGeometry
from ..io.atomic import write_text_atomic
from .common import pick_device, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="recover materials, SG lighting and the radiance cache", description=__doc__)
    p.add_argument("data", type=Path, help="dataset folder (any format nefii reads)")
    p.add_argument("--out", type=Path, required=True, help="run folder to write")
    p.add_argument("--preset", default="cpu", choices=sorted(PRESETS), help="starting configuration")
    p.add_argument("--mesh", type=Path, default=None, help="frozen geometry (default: the scene's mesh.ply)")
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
    if args.resume and (args.out / "config.json").is_file():
        saved = read_config(args.out)
        if args.overrides or args.preset != saved.preset:
            print("nefii fit: --resume continues with the run's own config.json; --preset/--set are ignored")
        cfg = saved
    return cfg


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    if not args.resume and (out / "checkpoints").exists():
        raise InputError(out, "already holds a run: use --resume to continue it, or another --out")
    cfg = fit_config(args)
    ctx = init_distributed(pick_device(args.device))
    try:
        return _fit(args, cfg, ctx)
    finally:
        shutdown(ctx)


def _fit(args: argparse.Namespace, cfg: FitConfig, ctx: DistContext) -> int:
    out: Path = args.out
    device = local_device(pick_device(args.device), ctx)
    threads = set_threads(cfg.threads)
    say = print if ctx.is_main else (lambda *a, **k: None)
    scene = load_scene(args.data, "train")
    source = resolve_source(args.mesh, args.geometry, scene.mesh_path, cfg.geometry_mode, args.data)
    cfg, source = adapt_to_source(cfg, source)
    geometry, features = source.open()
    box = tuple(torch.from_numpy(b.copy()) for b in geometry.bounds)
    what = f"mesh {source.mesh} ({len(geometry.faces)} triangles)" if isinstance(geometry, MeshGeometry) else \
        f"SDF of {source.folder}, sphere-traced, feature vector of {features.dim if features else 0}"
    if source.folder is not None:
        what += (f" (a reconstruction: material offset {cfg.material_offset:g}, normals smoothed to "
                 f"{source.normal_sigma:g} of the diagonal, the lookup's to {source.lookup_sigma:g}"
                 + (f", offset scaled to walls thinner than {source.lookup_separation:g}" if source.lookup_separation
                    else "") + ")")
    say(f"nefii fit: {len(scene)} views {scene.width}x{scene.height} from {scene.root} ({scene.format}); "
        f"{what}; device {device}, {threads} threads"
        + (f", {ctx.world_size} processes" if ctx.active else ""))
    pixels = first_hits(scene, geometry).to(device)
    say(f"nefii fit: {len(pixels.points)} object pixels, {len(pixels.bg_dirs)} background pixels")

    model = build_model(cfg, box, features)
    if not args.resume and cfg.light.kind == "sg" and cfg.light.init == "shading":
        pts = pixels.points
        est = estimate_light(pts.position, pts.normal, pts.geometric_normal, pixels.rgb, geometry,
                             generator=torch.Generator().manual_seed(cfg.seed), ray_offset=cfg.ray_offset)
        init = sg_from_light(est, cfg.light.num_lobes, sharp=cfg.light.sharpness_init_peak)
        set_sg_parameters(model.env, init)
        n_sharp = int((init.sharpness == cfg.light.sharpness_init_peak).sum())
        say(f"nefii fit: lighting initialised from shading and shadows ({n_sharp} sharp lobes)")
    trainer = Trainer(cfg, model, geometry, pixels, device, ctx)
    ckpt_dir = out / "checkpoints"
    if args.resume:
        last = Trainer.latest_checkpoint(ckpt_dir)
        if last is None:
            raise InputError(ckpt_dir, "no checkpoint to resume from")
        trainer.load_state_dict(torch.load(last, map_location=device, weights_only=False))
        say(f"nefii fit: resumed from {last} at step {trainer.step}")
    logger = None
    if ctx.is_main:
        out.mkdir(parents=True, exist_ok=True)
        ckpt_dir.mkdir(exist_ok=True)
        write_config(out, cfg)
        logger = RunLogger(out, cfg)
    t0, step0 = time.time(), trainer.step

    def preview(step: int) -> None:
        write_preview(out / "previews" / f"step_{step:07d}.png", trainer.model, geometry, scene,
                      view=(step // max(cfg.preview_every, 1)) % len(scene), transport=trainer.transport)

    try:
        trainer.fit(ckpt_dir, log=logger, progress=not args.quiet, preview=preview)
    except NonFiniteLoss as e:
        say(f"nefii fit: error: {e}; the last good checkpoint is in {ckpt_dir}")
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
        write_outputs(out, cfg, trainer.model, box, Path(args.data).resolve(), source)
        wall = time.time() - t0
        stats = {"steps": trainer.step, "steps_this_session": trainer.step - step0, "wall_s_this_session": wall,
                 "steps_per_s": (trainer.step - step0) / max(wall, 1e-9), "processes": ctx.world_size,
                 "threads": threads, "device": str(device),
                 "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}
        write_text_atomic(out / "fit_stats.json", json.dumps(stats, indent=2) + "\n")
        written = [n for n in ("model.pt", "envmap.exr", "sg.npy", "config.json", "fit_stats.json")
                   if (out / n).exists()]
        say(f"nefii fit: done, {trainer.step} steps; wrote {', '.join(written)} in {out}")
    return 0
