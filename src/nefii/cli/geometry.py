"""``nefii geometry DATA --out GEO``: the SDF stage (NeuS from the images, or fitted to ``--from-mesh``),
its marching-cubes mesh and normalisation, for data that comes without a mesh."""
from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import time
from pathlib import Path

import trimesh

from ..data import load_scene
from ..errors import InputError
from ..io.atomic import atomic_path, write_text_atomic
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


def _load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for bad files
        raise InputError(path, f"cannot read the mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(path, "the mesh has no triangles")
    return mesh


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    ckpt = out / "checkpoints"
    if not args.resume and ckpt.exists():
        raise InputError(out, "already holds a geometry run: use --resume to continue it, or another --out")
    cfg = _config(args)
    if args.resume and (out / "config.json").is_file():
        from ..sdf.config import geometry_config_from_dict
        cfg = geometry_config_from_dict(json.loads((out / "config.json").read_text()))
    device = pick_device(args.device)
    threads = set_threads(cfg.threads)
    scene = load_scene(args.data, "train")
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
    else:
        if args.masks == "on" and scene.masks is None:
            raise InputError(args.data, "--masks on, but the dataset has no masks (no mask files, no alpha)")
        masks = None if args.masks == "off" else scene.masks
        norm = normalization_from_cameras(scene.cameras, masks, root=args.data)
        objective = ImageObjective.from_views(cfg, scene, norm, masks, device)
        model = NeuSModel(cfg, background=masks is None)
        source = f"images ({'with' if masks is not None else 'without'} masks)"
        print(f"nefii geometry: NeuS on {len(scene)} views {scene.width}x{scene.height} from {scene.root}, "
              f"{'with masks' if masks is not None else 'no masks: NeRF++ background'}; unit sphere centre "
              f"{tuple(round(c, 4) for c in norm.center)}, radius {norm.radius:.4f}; device {device}, {threads} threads")
    trainer = GeometryTrainer(cfg, model, objective, device)
    if args.resume:
        if not trainer.resume(ckpt):
            raise InputError(ckpt, "no checkpoint to resume from")
        print(f"nefii geometry: resumed at step {trainer.step}")
    step0 = trainer.step
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "config.json", json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    try:
        trainer.fit(ckpt, progress=not args.quiet)
    except FloatingPointError as e:
        print(f"nefii geometry: error: {e}; the last good checkpoint is in {ckpt}")
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
             "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
             "mesh_vertices": len(mesh_out.vertices), "mesh_faces": len(mesh_out.faces)}
    write_text_atomic(out / "geometry_stats.json", json.dumps(stats, indent=2) + "\n")
    print(f"nefii geometry: done, {trainer.step - step0} steps in {stats['wall_s_this_session'] / 60:.1f} min; wrote sdf.pt, mesh.ply "
          f"({len(mesh_out.faces)} triangles), normalization.json in {out}")
    return 0
