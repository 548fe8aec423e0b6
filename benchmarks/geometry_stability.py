"""Does the geometry stage's image objective keep the true surface? A diagnostic of `nefii geometry`.

    python -m benchmarks.geometry_stability [--scenes cup bowl] [--mesh-steps 1500] [--image-steps 1000]
                                            [--jobs 2] [--set key=value ...] [--sharpness S] [--colour-steps K]

For each scene: the `cpu` preset's SDF network is fitted to the scene's own mesh.ply (the from-mesh
objective, in the normalisation the image objective uses), then trained on the images (NeuS, with
masks) for ``--image-steps`` more, starting from that SDF (after ``--colour-steps`` that train the
colour network alone, the SDF and ``s`` frozen, so that the joint steps do not start from an
untrained colour). The reconstruction measures (chamfer, normal error, share of the true surface
missed by more than 2% of the diagonal) are printed for the SDF before and after. If the images'
objective moves a surface it starts on, no schedule or initialisation of the geometry stage can be
expected to find that surface from a sphere: what is lost here is lost to the objective, not to the
optimisation. Writes
``benchmarks/results/geometry_stability.md``; meshes in ``benchmarks/.cache/geometry_stability``.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch
import trimesh

from nefii.data import load_scene
from nefii.sdf.config import resolve_geometry_config
from nefii.sdf.extract import extract_mesh
from nefii.sdf.from_mesh import MeshObjective, mesh_signed_distances
from nefii.sdf.metrics import MeshDistance, mesh_distance
from nefii.sdf.model import NeuSModel
from nefii.sdf.networks import Sharpness
from nefii.sdf.normalization import normalization_from_cameras
from nefii.sdf.train import GeometryTrainer, ImageObjective

from .common import CACHE, code_version, machine, scene, stamp, write_results


def one_scene(data: Path, mesh_steps: int, image_steps: int, sets: list[str], sharpness: float | None,
              colour_steps: int = 0) -> tuple[MeshDistance, MeshDistance, float]:
    """Distances of the mesh-fitted SDF and of the same SDF after the image steps to the scene's mesh, and
    the sharpness ``s`` the image steps started from."""
    torch.set_num_threads(1)
    tags = [*sets, *([f"s{sharpness:g}"] if sharpness is not None else []),
            *([f"colour{colour_steps}"] if colour_steps else [])]
    out = CACHE / "geometry_stability" / "_".join([data.name, *tags])
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device("cpu")
    views = load_scene(data, "train")
    if views.masks is None:
        raise ValueError(f"{data}: the diagnostic needs masks")
    norm = normalization_from_cameras(views.cameras, views.masks, root=data)
    # the from-mesh phase has no use for the coarse-to-fine schedule: the image phase starts with every level on
    cfg = resolve_geometry_config("cpu", [f"steps={mesh_steps}", "coarse_to_fine=0", *sets])
    truth = trimesh.load(data / "mesh.ply", force="mesh")
    model = NeuSModel(cfg, background=False)
    distances = mesh_signed_distances(truth, norm, 32 * cfg.from_mesh_points, seed=cfg.seed)
    GeometryTrainer(cfg, model, MeshObjective(cfg, distances), device).fit(out / "mesh_phase", progress=False)
    before = extract_mesh(model.sdf, norm, cfg.mesh_resolution, cfg.min_component)
    before.export(out / "mesh_fitted.ply")
    if sharpness is not None:  # a fresh sharpness module starting at s (``Sharpness(init)``: s = exp(10 init))
        model.sharpness = Sharpness(math.log(sharpness) / 10.0)
    s0 = float(model.sharpness().detach())
    # no cosine annealing: the SDF is already a surface, back faces have nothing to contribute
    image_cfg = dataclasses.replace(cfg, steps=image_steps, anneal_end=0.0)
    objective = ImageObjective.from_views(image_cfg, views, norm, views.masks, device)
    if colour_steps:
        frozen = [*model.sdf.parameters(), *model.sharpness.parameters()]
        for p in frozen:
            p.requires_grad_(False)
        colour_cfg = dataclasses.replace(image_cfg, steps=colour_steps)
        GeometryTrainer(colour_cfg, model, dataclasses.replace(objective, cfg=colour_cfg),  # the same rays
                        device).fit(out / "colour_phase", progress=False)
        for p in frozen:
            p.requires_grad_(True)
    GeometryTrainer(image_cfg, model, objective, device).fit(out / "image_phase", progress=False)
    after = extract_mesh(model.sdf, norm, cfg.mesh_resolution, cfg.min_component)
    after.export(out / "mesh_after_images.ply")
    return mesh_distance(before, truth), mesh_distance(after, truth), s0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["cup", "bowl"])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--views", type=int, default=64)
    ap.add_argument("--mesh-steps", type=int, default=1500)
    ap.add_argument("--image-steps", type=int, default=1000)
    ap.add_argument("--sharpness", type=float, default=None,
                    help="NeuS sharpness s the image steps start from (default: the network's initial value)")
    ap.add_argument("--colour-steps", type=int, default=0,
                    help="steps training only the colour network (SDF and s frozen) before the image steps")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--set", dest="extra", action="append", default=[], help="geometry-stage config override")
    args = ap.parse_args()
    datas = [scene(s, args.res, args.views) for s in args.scenes]
    t0 = time.time()
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(one_scene, datas, [args.mesh_steps] * len(datas), [args.image_steps] * len(datas),
                             [args.extra] * len(datas), [args.sharpness] * len(datas),
                             [args.colour_steps] * len(datas)))
    lines = [f"# geometry stability ({stamp()})", "",
             f"Machine: {machine()}. Scenes {args.res}x{args.res}, {args.views} training views, masks on; `cpu` "
             f"preset{' + ' + ' '.join(args.extra) if args.extra else ''}: {args.mesh_steps} steps fitting the SDF "
             f"to the scene's mesh.ply, then {args.colour_steps} steps training the colour network alone and "
             f"{args.image_steps} steps of the image objective from it "
             f"(no cosine annealing, every hash level on). {args.jobs} at a time, 1 thread each; "
             f"{(time.time() - t0) / 60:.1f} min; code {code_version()}.", "",
             "Chamfer and normal error as in geometry.md; 'missed': share of the scene mesh's surface farther than "
             "2% of the diagonal from the reconstruction. A surface the image objective keeps stays where the "
             "from-mesh fit put it.", "",
             "| scene | start s | chamfer % fitted / after images | normal deg fitted / after | missed fitted / after |",
             "|---|---|---|---|---|"]
    for name, (before, after, s0) in zip(args.scenes, rows):
        lines.append(f"| {name} | {s0:.0f} | {100 * before.chamfer_rel:.2f} / {100 * after.chamfer_rel:.2f} | "
                     f"{before.normal_deg:.1f} / {after.normal_deg:.1f} | {100 * before.missed:.1f}% / "
                     f"{100 * after.missed:.1f}% |")
    write_results("geometry_stability.md", lines)


if __name__ == "__main__":
    main()
