"""``nefii geometry DATA --out GEO``: the SDF stage (NeuS from the images, or fitted to ``--from-mesh``),
its marching-cubes mesh and normalisation, for data that comes without a mesh."""
from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..data import load_scene
from ..data.downscale import training_images
from ..data.fingerprint import fingerprint, require_same
from ..errors import InputError
from ..io.atomic import atomic_path, write_text_atomic
from ..raycast.mesh import check_faces
from ..run_folder import RunManifest, after_failure, resume_point, write_manifest, writing_run
from ..sdf.config import GEOMETRY_PRESETS, GeometryConfig, resolve_geometry_config
from ..sdf.extract import extract_mesh
from ..sdf.from_mesh import MeshObjective, mesh_signed_distances
from ..sdf.model import NeuSModel
from ..sdf.normalization import Normalization, normalization_from_cameras
from ..sdf.outputs import MESH_FILE, save_sdf
from ..sdf.train import GeometryTrainer, ImageObjective
from .common import pick_device, set_threads


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("geometry", help="reconstruct an SDF and mesh from the images (NeuS)", description=__doc__)
    p.add_argument("data", type=Path, help="dataset folder (any format nefii reads)")
    p.add_argument("--out", type=Path, required=True, help="geometry folder to write")
    p.add_argument("--preset", default="cpu", choices=sorted(GEOMETRY_PRESETS), help="starting configuration")
    p.add_argument("--masks", default="auto", choices=("auto", "on", "off"),
                   help="use the dataset's masks (auto: when it has some); off: a NeRF++ background separates the object")
    p.add_argument("--from-mesh", type=Path, default=None, metavar="MESH",
                   help="fit the SDF to this mesh instead of the images (synthetic evaluation)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint in --out")
    p.add_argument("--device", default="auto", help="cpu | cuda | cuda:N | auto")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set steps=500")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _config(args: argparse.Namespace) -> GeometryConfig:
    try:
        return resolve_geometry_config(args.preset, args.overrides)
    except (KeyError, ValueError) as e:
        raise InputError(None, f"bad configuration: {e.args[0] if e.args else e}") from None


def _read_config(path: Path) -> GeometryConfig:
    from ..sdf.config import geometry_config_from_dict
    try:
        return geometry_config_from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(path, f"not a valid nefii geometry config ({type(e).__name__}: {e})") from None


def _load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for bad files
        raise InputError(path, f"cannot read the mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "the mesh has no triangles")
    check_faces(np.asarray(mesh.faces), len(mesh.vertices), path)
    if not np.isfinite(mesh.vertices).all():
        raise InputError(path, "mesh has NaN/inf vertex coordinates")
    return mesh


def run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    device = pick_device(args.device)
    with writing_run(args.out, "geometry", args.resume, warn=_warn) as manifest:
        return _geometry(args, cfg, device, manifest)


def _warn(line: str) -> None:
    print(f"nefii geometry: warning: {line}", file=sys.stderr)


def _geometry(args: argparse.Namespace, cfg: GeometryConfig, device: torch.device, manifest: RunManifest | None) -> int:
    out: Path = args.out
    ckpt = out / "checkpoints"
    checkpoint = None
    if args.resume:
        if manifest is not None and (out / "config.json").is_file():
            cfg = _read_config(out / "config.json")
        checkpoint = resume_point(out, "geometry", manifest, _warn, lambda line: print(f"nefii geometry: {line}"))
    threads = set_threads(cfg.threads)
    if cfg.preset == "gpu" and device.type == "cpu":
        cpu, gpu = resolve_geometry_config("cpu", []), resolve_geometry_config("gpu", [])
        ratio = gpu.batch_rays * gpu.steps / (cpu.batch_rays * cpu.steps)
        _warn(f"the gpu preset on the CPU casts {ratio:.1f} times the cpu preset's rays in all (use --device cuda, "
              "or --preset cpu)")
    scene = load_scene(args.data, "train")
    scene, line = training_images(scene, cfg.max_image_side)
    if line:
        print(f"nefii geometry: {line}")
    t0 = time.time()
    if args.from_mesh is not None:
        mesh = _load_mesh(args.from_mesh)
        lo, hi = mesh.bounds
        norm = Normalization(tuple(float(c) for c in 0.5 * (lo + hi)), float(0.5 * 1.15 * ((hi - lo) ** 2).sum() ** 0.5))
        print(f"nefii geometry: fitting the SDF to {args.from_mesh} ({len(mesh.faces)} triangles)")
        data = mesh_signed_distances(mesh, norm, 32 * cfg.from_mesh_points, seed=cfg.seed)
        data = type(data)(data.points.to(device), data.sdf.to(device))
        objective = MeshObjective(cfg, data)
        model = NeuSModel(cfg, background=False)
        source = f"mesh {args.from_mesh}"
        unit = 1.0                                        # no colours
    else:
        if args.masks == "on" and scene.masks is None:
            raise InputError(args.data, "--masks on, but the dataset has no masks (no mask files, no alpha)")
        masks = None if args.masks == "off" else scene.masks
        norm = normalization_from_cameras(scene.cameras, masks, root=args.data)
        objective = ImageObjective.from_views(cfg, scene, norm, masks, device)
        unit = objective.unit
        if unit != 1.0:
            print(f"nefii geometry: the images are {'brighter' if unit > 1.0 else 'darker'} than the stage "
                  f"is made for: colours taken in units of {unit:.4g}")
        model = NeuSModel(cfg, background=masks is None, num_views=len(scene))
        source = f"images ({'with' if masks is not None else 'without'} masks)"
        print(f"nefii geometry: NeuS on {len(scene)} views {scene.width}x{scene.height} from {scene.root}, "
              f"{'with masks' if masks is not None else 'no masks: NeRF++ background'}"
              f"{', a gain per view' if model.gains is not None else ''}; unit sphere centre "
              f"{tuple(round(c, 4) for c in norm.center)}, radius {norm.radius:.4f}; device {device}, {threads} threads")
    data_print = fingerprint(scene, args.from_mesh)
    if checkpoint is not None and manifest is not None and manifest.data is not None:
        require_same(manifest.data, data_print, out)
    trainer = GeometryTrainer(cfg, model, objective, device)
    if checkpoint is not None:
        trainer.resume(checkpoint)
        print(f"nefii geometry: resumed from {checkpoint.path} at step {trainer.step}")
    step0 = trainer.step
    out.mkdir(parents=True, exist_ok=True)
    write_manifest(out, RunManifest("geometry", data_print))
    write_text_atomic(out / "config.json", json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    try:
        trainer.fit(ckpt, progress=not args.quiet)
    except FloatingPointError as e:
        print(f"nefii geometry: error: {e}; {after_failure(out)}")
        return 1
    save_sdf(out, cfg, model.sdf, norm, source)
    try:
        mesh_out = extract_mesh(model.sdf, norm, cfg.mesh_resolution, cfg.min_component)
    except ValueError as e:
        print(f"nefii geometry: error: {e}")
        return 1
    with atomic_path(out / MESH_FILE) as tmp:
        mesh_out.export(tmp)
    stats = {"steps": trainer.step, "steps_this_session": trainer.step - step0, "wall_s_this_session": time.time() - t0,
             "source": source,
             "radiance_unit": unit,
             "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
             "mesh_vertices": len(mesh_out.vertices), "mesh_faces": len(mesh_out.faces)}
    write_text_atomic(out / "geometry_stats.json", json.dumps(stats, indent=2) + "\n")
    print(f"nefii geometry: done, {trainer.step - step0} steps in {stats['wall_s_this_session'] / 60:.1f} min; wrote sdf.pt, mesh.ply "
          f"({len(mesh_out.faces)} triangles), normalization.json in {out}")
    return 0
