"""The geometry stage on the built-in scenes: reconstructed mesh against the scene's mesh.ply, and the
fit's albedo / roughness with reconstructed against ground-truth geometry.

    python -m benchmarks.geometry [--scenes bowl cup ...] [--res 128] [--views 64] [--masks on off]
                                  [--fits [SCENE ...]] [--refine] [--fit-res 128] [--jobs 2] [--preset cpu]
                                  [--set key=value ...]

For each scene (and each masks setting) runs ``nefii geometry`` (``--preset``, default ``cpu``) and measures the
chamfer distance (relative to the scene's bounding-box diagonal), the share of the true surface missed (of all of
it, and of the part some training view sees: the underside of a floor slab or a saucer is in no image) and normal
angle error against ``mesh.ply``, wall time and peak memory. With ``--fits``, also ``nefii fit`` + ``nefii eval`` on
the reconstructed geometry (mesh mode) beside the ground-truth-geometry fit that
``benchmarks.quality`` caches. With ``--refine``, each fit on a reconstruction is copied and refined by
``nefii refine`` (default settings), its refined mesh measured as the reconstruction is and the copy evaluated.
Runs live in ``benchmarks/.cache/geometry``, in a folder per scene, masks and resolved stage settings, and are
reused only at the same settings.
Writes ``benchmarks/results/geometry.md``.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
import trimesh

from nefii.camera import jittered_pixel_rays
from nefii.data import load_scene
from nefii.data.material import load_material
from nefii.evaluate.partial import view_seed
from nefii.evaluate.render_views import MAX_SUBPIXELS, render_view, subpixel_grid, subpixel_samples
from nefii.evaluate.run import eval_mask, ground_truth
from nefii.evaluate.table1 import ViewArrays, mean_scores, view_scores
from nefii.fit.outputs import load_run
from nefii.raycast import MeshGeometry, Rays
from nefii.sdf.config import GEOMETRY_PRESETS, resolve_geometry_config
from nefii.sdf.metrics import MeshDistance, mesh_distance

from .common import (CACHE, all_steps_wall_min, code_version, fit_and_eval, machine, nefii, scene, set_flags,
                     settings_digest, stamp, write_results)
from .quality import run_dir, run_one


_ASIDE = ("threads", "checkpoint_every_s")
"""stage settings that do not change what a stage computes"""


def geometry_folder(data_name: str, masks: str, preset: str, extra: list[str]) -> Path:
    """The cached stage's folder: named by the scene, the masks, the preset, the overrides and a digest of the
    settings the stage resolves to (threads and checkpointing aside), so that neither a variant nor a run made
    at other defaults (an older preset's steps) stands in for the one asked for."""
    named = [kv.replace("/", "-") for kv in extra if kv.split("=")[0] not in _ASIDE]
    return CACHE / "geometry" / "_".join([f"{data_name}_masks_{masks}", preset, *named, stage_digest(preset, extra)])


def stage_digest(preset: str, extra: list[str]) -> str:
    """:func:`settings_digest` of the settings the geometry stage resolves to (threads and checkpointing aside): a
    cached stage, or a run that made one, is reused only where they match."""
    return settings_digest(resolve_geometry_config(preset, extra), _ASIDE)


def geometry_run(data: Path, name: str, masks: str, threads: int, extra: list[str], preset: str) -> dict:
    out = geometry_folder(data.name, masks, preset, extra)
    if not (out / "geometry_stats.json").exists():
        sets = set_flags(extra, threads)
        resume = ["--resume"] if (out / "checkpoints").exists() else []
        nefii("geometry", str(data), "--out", str(out), "--masks", masks, "--preset", preset, "--quiet", *resume,
              *sets)
    stats = json.loads((out / "geometry_stats.json").read_text())
    d = measured(out / "mesh.ply", data)
    wall_min, resumed = all_steps_wall_min(stats)
    return {"scene": name, "masks": masks, "chamfer_rel": d.chamfer_rel, "normal_deg": d.normal_deg, "missed": d.missed,
            "missed_seen": d.missed_seen, "seen": d.seen, "normal_median": d.normal_median_covered_deg,
            "wall_min": wall_min, "resumed": resumed,
            "peak_gib": stats["peak_rss_gib"],
            "folder": out, "code": code_version()}


def measured(mesh: Path, data: Path) -> MeshDistance:
    """``mesh`` against the scene ``data``'s own, with the share of it the training views see."""
    return mesh_distance(trimesh.load(mesh, force="mesh"), trimesh.load(data / "mesh.ply", force="mesh"),
                         cameras=load_scene(data, "train").cameras)


def fit_on(data: Path, geo: Path, threads: int, sets: list[str], tag: str) -> dict:
    """``nefii fit --geometry geo`` (mesh mode, the ``cpu`` preset + ``sets``) on ``data``, evaluated; the
    masked metrics. The run is ``geo/fit_<data>`` (``_<tag>`` appended when given)."""
    run = geo / (f"fit_{data.name}" + (f"_{tag}" if tag else ""))
    fit_and_eval(data, run, ["--geometry", str(geo), *set_flags(sets, threads)], 64, f"{data.name} on {geo}", sets)
    return json.loads((run / "eval" / "metrics.json").read_text())["masked"]


RUN_FILES = ("model.pt", "config.json", "run.json", "envmap.exr", "sg.npy", "fit_stats.json")


def refine_on(data: Path, geo: Path, threads: int, tag: str) -> dict:
    """``nefii refine`` on a copy of :func:`fit_on`'s run (``..._refined``), evaluated: its masked metrics, the refined
    mesh against the scene's and the refinement's wall time."""
    fitted = geo / (f"fit_{data.name}" + (f"_{tag}" if tag else ""))
    run = fitted.with_name(fitted.name + "_refined")
    if not (run / "eval" / "metrics.json").exists():
        if not (run / "refined" / "sdf.pt").exists():
            run.mkdir(exist_ok=True)
            for name in RUN_FILES:
                if (fitted / name).exists() and not (run / name).exists():
                    shutil.copy2(fitted / name, run / name)
            resume = ["--resume"] if (run / "refined" / "checkpoints").exists() else []
            nefii("refine", str(run), "--quiet", "--set", f"threads={threads}", *resume)
        nefii("eval", str(run), "--quiet", "--spp", "64")
    stats = json.loads((run / "refined" / "refine_stats.json").read_text())
    d = measured(run / "refined" / "mesh.ply", data)
    geometry_min, resumed = all_steps_wall_min(stats)
    materials_min = stats["materials_wall_s_this_session"] / 60
    return {"metrics": json.loads((run / "eval" / "metrics.json").read_text())["masked"], "chamfer_rel": d.chamfer_rel,
            "normal_deg": d.normal_deg, "normal_median": d.normal_median_covered_deg, "missed": d.missed,
            "missed_seen": d.missed_seen, "wall_min": geometry_min + materials_min, "geometry_min": geometry_min,
            "resumed": resumed}


@torch.no_grad()
def albedo_on(run: Path, mesh: Path) -> float:
    """Masked albedo PSNR (Table 1 scoring) of ``run``'s fitted material read at ``mesh``'s first hits in the test
    views by eval's own material pass (``nefii eval --material-only``: each pixel the mean over 4 x 4 sub-pixel
    rays, the view's generator seeded as eval seeds it), so on the run's own mesh it is that eval's score to the
    bit. (Read at pixel centres instead, the true-mesh fits' own materials scored 2.5-6 dB below their evals on the
    true meshes: the protocol's loss, not the geometry's.) With the ground-truth-geometry fit and a reconstructed
    mesh: how well that fit's field transfers to another surface. Not a bound on a fit on the reconstruction (a
    field reads its texture through the surface it was fitted on: the bowl's maskless photo reconstruction scored
    the true-mesh fit's material at 26.96 dB, and the capture's own fit on it at 29.73); :func:`truth_on` is the
    geometry's share."""
    fitted = load_run(run)
    views = load_scene(fitted.data, "test")
    geometry = MeshGeometry.from_file(mesh)
    scores = []
    for v in range(len(views)):
        g = torch.Generator().manual_seed(view_seed(0, views.indices[v]))
        pred = render_view(fitted.model, geometry, views.cameras, v, 0, g)
        truth = ground_truth(views, v)
        arrays = ViewArrays(truth.rgb, pred.albedo.cpu().numpy(), None, None)
        mask = eval_mask(views, v, pred.mask.cpu().numpy())
        scores.append(view_scores(arrays, ViewArrays(truth.rgb, truth.albedo, None, None), mask)[0])
    return mean_scores(scores)["masked"]["albedo_psnr"]


PROJECTION = 0.01
"""how far along its own normal (times the scene mesh's scale, either way) a reconstruction's hit is carried onto
the true surface by :func:`truth_on`"""


@dataclass(frozen=True)
class TruthOnRecon:
    albedo_psnr: float
    """masked albedo PSNR of the true material read at the reconstruction's hits"""
    unprojected: float
    """share of the hit rays with no true surface within the projection (a lid over a hollow, say)"""


@torch.no_grad()
def truth_on(data: Path, mesh: Path, seed: int = 0) -> TruthOnRecon:
    """The scene's *true* material read where the test views' rays hit ``mesh`` (each hit carried onto the true
    surface along ``mesh``'s normal, within :data:`PROJECTION` of the scale), eval's 4 x 4 sub-pixel mean and mask,
    scored as eval scores: the albedo error the reconstruction's misplaced hits make with a perfect material. A ray
    with no true surface there reads the true surface its own ray hits (as a surface painted for that view would
    show: optimistic on a lid), and their share is returned beside the score."""
    views = load_scene(data, "test")
    true_mesh = MeshGeometry.from_file(views.mesh_path)
    material = load_material(data)
    geometry = MeshGeometry.from_file(mesh)
    reach = PROJECTION * true_mesh.scale
    generator = torch.Generator().manual_seed(seed)
    k = subpixel_grid(MAX_SUBPIXELS)
    scores, unprojected, rays = [], 0, 0
    for v in range(len(views)):
        H, W = views.height, views.width
        pixel, u = subpixel_samples(H * W, k, generator, "cpu")
        o, d = jittered_pixel_rays(views.cameras.c2w[v], views.cameras.K[v], W, pixel, u)
        o, d = o.float(), d.float()
        hit = geometry.intersect(Rays(o, d))
        idx = hit.valid.nonzero().squeeze(-1)
        n = hit.normal[idx]
        onto = true_mesh.intersect(Rays(hit.position[idx] + reach * n, -n))
        carried = onto.valid & (onto.t <= 2 * reach)
        own = true_mesh.intersect(Rays(o[idx], d[idx]))
        position = torch.where(carried.unsqueeze(-1), onto.position, own.position)
        triangle = torch.where(carried, onto.triangle_id, own.triangle_id)
        keep = carried | own.valid
        unprojected, rays = unprojected + int((~carried).sum()), rays + len(idx)
        albedo = material.at_hits(true_mesh, triangle[keep], position[keep]).albedo
        p = pixel[idx][keep]
        count = torch.zeros(H * W).index_add_(0, pixel[idx], torch.ones(len(idx)))
        total = torch.zeros(H * W, 3).index_add_(0, p, albedo)
        seen = torch.zeros(H * W).index_add_(0, p, torch.ones(len(p)))
        image = (total / seen.clamp_min(1).unsqueeze(-1)).reshape(H, W, 3).numpy()
        gt = ground_truth(views, v)
        mask = eval_mask(views, v, (count >= k * k / 2).reshape(H, W).numpy())
        scores.append(view_scores(ViewArrays(gt.rgb, image, None, None), ViewArrays(gt.rgb, gt.albedo, None, None),
                                  mask)[0])
    return TruthOnRecon(mean_scores(scores)["masked"]["albedo_psnr"], unprojected / max(rays, 1))


def ground_truth_fit(name: str, data: Path, threads: int) -> dict:
    """The full model on the scene's own mesh: ``benchmarks.quality``'s run, fitted here if missing."""
    run_one(data, name, "full", [], threads, 64)
    return json.loads((run_dir(name, "full") / "eval" / "metrics.json").read_text())["masked"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=["bowl", "leaning", "cup", "corner"])
    ap.add_argument("--masks", nargs="+", default=["on"], choices=["on", "off"])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--views", type=int, default=64)
    ap.add_argument("--fits", nargs="*", metavar="SCENE", default=None,
                    help="also fit materials on the reconstructed geometry (of these scenes; none named: all), at "
                         "--fit-res, beside benchmarks.quality's fit on the ground-truth mesh")
    ap.add_argument("--refine", action="store_true", help="also refine each fit on a reconstruction (nefii refine)")
    ap.add_argument("--fit-res", type=int, default=128)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--preset", default="cpu", choices=sorted(GEOMETRY_PRESETS),
                    help="the geometry stage's preset (gpu: run where a GPU is)")
    ap.add_argument("--set", dest="extra", action="append", default=[], help="geometry-stage config override")
    ap.add_argument("--fit-set", dest="fit_sets", action="append", default=[], metavar="KEY=VALUE",
                    help="fit config override for the fits on the reconstructions (give --fit-tag with it)")
    ap.add_argument("--fit-tag", default="", help="name of these fits' variant: runs fit_<scene>_<tag>")
    ap.add_argument("--note", default="", help="a sentence for the results file (how the cached runs were made)")
    args = ap.parse_args()
    if args.fit_sets and not args.fit_tag:
        ap.error("--fit-set needs --fit-tag (the variant's runs must not reuse the preset's)")
    threads = 1 if args.jobs > 1 else 0
    datas = {s: scene(s, args.res, args.views) for s in args.scenes}
    t0 = time.time()
    jobs = [(datas[s], s, m) for s in args.scenes for m in args.masks]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda j: geometry_run(*j, threads, args.extra, args.preset), jobs))
    fitted = [r for r in rows if args.fits is not None and (not args.fits or r["scene"] in args.fits)]
    with ThreadPoolExecutor(args.jobs) as pool:
        fits = list(pool.map(lambda r: fit_on(scene(r["scene"], args.fit_res, args.views), r["folder"], threads,
                                              args.fit_sets, args.fit_tag), fitted))
        gts = list(pool.map(lambda r: ground_truth_fit(r["scene"], scene(r["scene"], args.fit_res, args.views),
                                                       threads), fitted))
        refined = list(pool.map(lambda r: refine_on(scene(r["scene"], args.fit_res, args.views), r["folder"], threads,
                                                    args.fit_tag), fitted)) if args.refine else []
    for r, f in zip(fitted, refined):
        r["refined"] = f
    for r, f, g in zip(fitted, fits, gts):
        r["fit"], r["gt_fit"] = f, g
        r["transplant"] = albedo_on(run_dir(r["scene"], "full"), r["folder"] / "mesh.ply")
        r["truth_on"] = truth_on(scene(r["scene"], args.fit_res, args.views), r["folder"] / "mesh.ply")
    any_fit = bool(fitted)
    lines = [f"# geometry ({stamp()})", "",
             f"Machine: {machine()}. Scenes {args.res}x{args.res}, {args.views} training views; `nefii geometry` "
             f"`{args.preset}` preset{' + ' + ' '.join(args.extra) if args.extra else ''}; {args.jobs} at a time "
             f"({threads or 'all'} thread(s) each). This invocation {(time.time() - t0) / 60:.1f} min; "
             f"code {code_version()}.", *([args.note] if args.note else []), "",
             "Chamfer: mean of both directed mean nearest-neighbour distances over 100k surface samples each, "
             "relative to the scene mesh's bounding-box diagonal (target <= 1%). Wall time marked * is a "
             "resumed run's last session scaled to all its steps. Missed: share of the scene mesh's surface farther "
             "than 2% of the diagonal from the reconstruction (a lidded hollow's inside, say), of all of it and of the part "
             "some training view sees (what images can recover; the seen share in brackets). Normal error: the mean "
             "angle of nearest-neighbour pairs both ways, and the median over the scene mesh's surface within 1% of "
             "the diagonal of the reconstruction (what it covers).", "",
             *([f"Fits: `nefii fit --geometry` (mesh mode, `cpu` preset"
                f"{' + ' + ' '.join(args.fit_sets) if args.fit_sets else ''}) on the {args.fit_res}x{args.fit_res} "
                f"scene with the mesh reconstructed above, beside the same fit on the scene's own mesh "
                f"(`benchmarks.quality`'s `full` run); masked albedo PSNR (target: within 1.5 dB) and roughness MSE. "
                f"'GT material on recon' is the ground-truth-geometry fit's material read at the reconstructed "
                f"mesh's first hits by eval's material pass and scored the same way: how well that fit's field "
                f"transfers to another surface, not a bound (a field reads a texture through the surface it was "
                f"fitted on). 'True material on recon' is the scene's true material read at the reconstruction's hits "
                f"(each carried onto the true surface along the reconstruction's normal, within "
                f"{100 * PROJECTION:.0f}% of the scale; in brackets the share of rays with no true surface there, a "
                f"lid's, read at their own ray's true hit, which is optimistic), box-filtered as eval's layers are: "
                f"what the misplaced hits alone cost a perfect material (the true mesh scores the protocol's own "
                f"ceiling, 38-48 dB on the built-in scenes).", ""]
               if any_fit else []),
             "| scene | masks | chamfer (% diag) | missed: all / seen (seen share) | "
             "normal error mean / covered median (deg) | wall min | "
             "peak GiB |"
             + (" albedo PSNR recon / GT geometry | GT material on recon | true material on recon | "
                "roughness MSE recon / GT geometry |" if any_fit else ""),
             "|---|---|---|---|---|---|---|" + ("---|---|---|---|" if any_fit else "")]
    for r in rows:
        line = (f"| {r['scene']} | {r['masks']} | {100 * r['chamfer_rel']:.2f} | {_missed(r)} | "
                f"{r['normal_deg']:.1f} / {r['normal_median']:.1f} | "
                f"{r['wall_min']:.1f}{'*' if r['resumed'] else ''} | {r['peak_gib']:.2f} |")
        if "fit" in r:
            t = r["truth_on"]
            line += (f" {r['fit']['albedo_psnr']:.2f} / {r['gt_fit']['albedo_psnr']:.2f} | {r['transplant']:.2f} | "
                     f"{t.albedo_psnr:.2f} ({100 * t.unprojected:.1f}%) | "
                     f"{r['fit']['roughness_mse']:.4f} / {r['gt_fit']['roughness_mse']:.4f} |")
        elif any_fit:
            line += " | | | |"
        lines.append(line)
    if any("refined" in r for r in rows):
        lines += ["", "Refined (`nefii refine`, default settings, on a copy of each fit above: the geometry refined, "
                  "then the materials fitted again on it): the refined mesh measured as the reconstruction is, and the "
                  "refined run evaluated (masked albedo PSNR and roughness MSE: refined / before refinement / "
                  "ground-truth geometry). Minutes: both phases (the geometry's in brackets). Targets: normal error "
                  "<= 5 degrees, missed <= 5%, albedo within 1.0 dB and roughness MSE within 1.5x of the "
                  "ground-truth-geometry fit.", "",
                  "| scene | chamfer (% diag) | missed: all / seen | normal error mean / covered median (deg) | "
                  "refine min | "
                  "albedo PSNR | roughness MSE |",
                  "|---|---|---|---|---|---|---|"]
        for r in rows:
            if "refined" not in r:
                continue
            f, m = r["refined"], r["refined"]["metrics"]
            lines.append(f"| {r['scene']} | {100 * f['chamfer_rel']:.2f} | {_missed(f)} | "
                         f"{f['normal_deg']:.1f} / {f['normal_median']:.1f} | {f['wall_min']:.1f} "
                         f"({f['geometry_min']:.1f}{'*' if f['resumed'] else ''}) | "
                         f"{m['albedo_psnr']:.2f} / {r['fit']['albedo_psnr']:.2f} / {r['gt_fit']['albedo_psnr']:.2f} | "
                         f"{m['roughness_mse']:.4f} / {r['fit']['roughness_mse']:.4f} / "
                         f"{r['gt_fit']['roughness_mse']:.4f} |")
    write_results("geometry.md", lines)


def _missed(r: dict) -> str:
    """The missed shares of a row (an older cached row has no seen share)."""
    text = f"{100 * r['missed']:.1f}%"
    if not math.isnan(r.get("missed_seen", math.nan)):
        text += f" / {100 * r['missed_seen']:.1f}%"
    if not math.isnan(r.get("seen", math.nan)):
        text += f" ({100 * r['seen']:.1f}%)"
    return text


if __name__ == "__main__":
    main()
