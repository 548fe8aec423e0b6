"""nefii side by side with a peer, Mitsuba 3 inverse rendering, on the built-in scenes.

    python -m benchmarks.peers.mitsuba_inverse [--scenes bowl cup] [--budget-s S] [--threads 1]
        [--res 128 --views 64] [--jobs 2] [--skip-nefii] [--no-curve] [--force] [--set KEY=VALUE]
        [--peer-lr-env 0.2 ...]  (every PeerConfig field has a --peer-* flag)

Per scene, on the same data, mesh, test views and eval code:

* nefii ``full``, ``light_envmap`` (the env-map-grid baseline) and ``physg`` (``visibility=off,
  indirect=off``, the PhySG-style baseline): ``benchmarks.quality``'s runs, reused when complete
  and fitted (``cpu`` preset, ``--threads`` each) when missing, unless ``--skip-nefii``;
* the Mitsuba peer (``mitsuba_peer``) for the wall-clock budget of nefii full's fit on that scene
  (or ``--budget-s``), then scored by ``peer_eval``; cached in ``benchmarks/.cache/peers/<scene>/``
  (textures, env map, curve.csv, result.json, eval/);
* nefii's albedo PSNR over fitting time (``nefii_curve``), unless ``--no-curve``.

Ends by writing ``benchmarks/results/peers.md`` and ``peers.png`` (``benchmarks.peers.report``). Each
fit runs in its own process (``--worker``), so its peak RSS is its own; ``--jobs`` of them at a time.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata as md
import json
import math
import os
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .. import common, quality
from .hits import SUBPIXELS
from .mitsuba_peer import PeerConfig
from .report import SCENES, peer_dir, write_report

NEFII_CONFIGS = ("full", "light_envmap", "physg")
HITS_PROTOCOL = f"{SUBPIXELS}x{SUBPIXELS} sub-pixel rays, averaged per pixel"
"""how the material is read (``benchmarks.peers.hits``); a cached run read another way is rerun"""


def gib(maxrss_kib: int) -> float:
    return maxrss_kib / 2**20


# ---------------------------------------------------------------- workers (one process each)

def peer_worker(data: Path, out: Path, budget_s: float, cfg: PeerConfig, eval_spp: int, checks: int,
                max_steps: int | None = None) -> dict:
    """Fit the peer on ``data`` for ``budget_s`` seconds of steps, score it, write ``out``."""
    import torch

    from nefii.data import load_scene
    from nefii.raycast import MeshGeometry
    from nefii.io.atomic import write_text_atomic
    from nefii.io.exr import write_exr
    from nefii.io.images import write_png

    from .mitsuba_peer import MitsubaPeer, atlas_mesh, camera_rig, config_record, premultiplied_images, \
        textures_at_hits
    from .peer_eval import evaluate
    from .hits import cast_test_views, hit_uv, material_scores, scatter

    torch.set_num_threads(cfg.threads)
    t0 = time.perf_counter()
    train, test = load_scene(data, "train"), load_scene(data, "test")
    geometry = MeshGeometry.from_file(train.mesh_path, threads=cfg.threads)  # nefii's mesh and normals
    mesh = atlas_mesh(geometry.vertices, geometry.faces, geometry.vertex_normals, cfg.texture_size)
    peer = MitsubaPeer(mesh, camera_rig(train), premultiplied_images(train), cfg)
    views = cast_test_views(test, geometry)
    uvs = [hit_uv(h, mesh) for h in views.hits]
    setup_s = time.perf_counter() - t0

    checked: dict[int, dict] = {}

    def check(p: MitsubaPeer, fit_s: float) -> None:
        checked[p.step] = material_scores(views, *textures_at_hits(p.mi, views, uvs, *p.textures()))

    loss_before = peer.mean_image_loss()
    fit = peer.fit(budget_s, max_steps, check, budget_s / checks if max_steps is None else math.inf)
    loss_after = peer.mean_image_loss()
    if fit.steps not in checked:
        check(peer, fit.fit_s)
    peak_fit = gib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)

    out.mkdir(parents=True, exist_ok=True)
    write_exr(out / "base_color.exr", fit.base_color)
    write_exr(out / "roughness.exr", fit.roughness)
    write_exr(out / "envmap.exr", fit.envmap)
    write_png(out / "base_color.png", np.clip(fit.base_color, 0, 1))
    keys = ("albedo_psnr", "albedo_ssim", "roughness_mse")
    lines = ["step,fit_s,loss," + ",".join(keys)]
    for rec in fit.log:
        s = checked.get(rec.step)
        cells = ["" if s is None or s[k] is None else f"{s[k]:.6g}" for k in keys]
        lines.append(f"{rec.step},{rec.fit_s:.3f},{rec.loss:.6g}," + ",".join(cells))
    write_text_atomic(out / "curve.csv", "\n".join(lines) + "\n")

    means = evaluate(test, views, uvs, mesh, fit, out / "eval", eval_spp, cfg.seed, cfg.threads)
    grey = [scatter(h, np.full((len(h.position), 3), 0.5, np.float32)) for h in views.hits]
    half = [scatter(h, np.full(len(h.position), 0.5, np.float32)) for h in views.hits]
    result = {
        "scene": test.root.name, "data": str(data), "budget_s": budget_s, "fit_s": fit.fit_s, "steps": fit.steps,
        "setup_s": setup_s, "peak_rss_gib_fit": peak_fit,
        "peak_rss_gib_with_eval": gib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss),
        "config": config_record(cfg), "eval_spp": eval_spp, "max_steps": max_steps, "hits": HITS_PROTOCOL,
        "loss_all_training_views": {"before": loss_before, "after": loss_after, "spp": 16},
        "mesh": {"vertices": len(geometry.vertices), "triangles": len(geometry.faces),
                 "atlas_vertices": len(mesh.vertices)},
        "eval": means,
        "reference": {"constant_albedo": material_scores(views, grey, half)},
        "code": common.code_version(),
        "versions": versions(),
    }
    write_text_atomic(out / "result.json", json.dumps(result, indent=2) + "\n")
    return result


def curve_worker(data: Path, out: Path, threads: int, every: int, overrides: list[str],
                 max_steps: int | None = None) -> None:
    from nefii.io.atomic import write_text_atomic

    from .nefii_curve import run_curve, write_curve_csv

    points, cfg, fit_s = run_curve(data, threads, every, overrides, max_steps=max_steps)
    write_curve_csv(out / "nefii_curve.csv", points)
    write_text_atomic(out / "nefii_curve.json", json.dumps({
        "data": str(data), "preset": cfg.preset, "threads": threads, "steps": points[-1].step, "fit_s": fit_s,
        "hits": HITS_PROTOCOL,
        "peak_rss_gib": gib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss), "every": every, "sets": overrides,
        "code": common.code_version()}, indent=2) + "\n")


def versions() -> dict:
    out = {}
    for dist in ("mitsuba", "drjit", "torch", "numpy", "embreex", "xatlas"):
        try:
            out[dist] = md.version(dist)
        except md.PackageNotFoundError:
            out[dist] = None
    return out


# ---------------------------------------------------------------- orchestration

def run_worker(args: list[str], what: str, threads: int) -> None:
    env = dict(os.environ, OMP_NUM_THREADS=str(max(threads, 1)))
    proc = subprocess.run([sys.executable, "-m", "benchmarks.peers.mitsuba_inverse", *args], capture_output=True,
                          text=True, env=env, cwd=common.REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{proc.stderr[-3000:]}")


def peer_is_current(out: Path, data: Path, budget_s: float, cfg: PeerConfig, eval_spp: int) -> bool:
    f = out / "result.json"
    if not f.is_file():
        return False
    res = json.loads(f.read_text())
    same = {k: v for k, v in res["config"].items() if k in dataclasses.asdict(cfg)} == dataclasses.asdict(cfg)
    return same and abs(res["budget_s"] - budget_s) < 1.0 and res["eval_spp"] == eval_spp and \
        res["data"] == str(data) and res.get("hits") == HITS_PROTOCOL


def curve_is_current(out: Path, data: Path, extra: list[str]) -> bool:
    f = out / "nefii_curve.json"
    if not (f.is_file() and (out / "nefii_curve.csv").is_file()):
        return False
    rec = json.loads(f.read_text())
    return rec["data"] == str(data) and rec.get("sets", []) == extra and rec.get("hits") == HITS_PROTOCOL


def budget_for(name: str, override: float | None) -> float:
    if override is not None:
        return override
    row = quality.read_row(name, "full")
    if row is None:
        raise SystemExit(f"peers: no completed nefii full run for {name} to take the budget from; run without "
                         "--skip-nefii or give --budget-s")
    return float(row["fit_s"])


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces this invocation's runs."""
    cmd = "python -m benchmarks.peers.mitsuba_inverse --scenes " + " ".join(args.scenes)
    if os.environ.get("NEFII_BENCH_CACHE"):
        cmd = f"NEFII_BENCH_CACHE={os.environ['NEFII_BENCH_CACHE']} " + cmd
    if args.budget_s is not None:
        cmd += f" --budget-s {args.budget_s:g}"
    if args.threads != 1:
        cmd += f" --threads {args.threads}"
    if (args.res, args.views, args.test_views) != (128, 64, 8):
        cmd += f" --res {args.res} --views {args.views} --test-views {args.test_views}"
    return cmd + "".join(f" --set {kv}" for kv in args.extra)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES[:2]))
    ap.add_argument("--budget-s", type=float, default=None, help="peer budget (default: nefii full's fit time)")
    ap.add_argument("--threads", type=int, default=1, help="threads of every fit (nefii and the peer)")
    ap.add_argument("--jobs", type=int, default=2, help="fits at a time")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--views", type=int, default=64)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--eval-spp", type=int, default=64)
    ap.add_argument("--checks", type=int, default=30, help="albedo evaluations along the peer's curve")
    ap.add_argument("--curve-every", type=int, default=100, help="steps between albedo evaluations of nefii's curve")
    ap.add_argument("--curve-max-steps", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--skip-nefii", action="store_true", help="fit nothing with nefii; use the runs that exist")
    ap.add_argument("--no-curve", action="store_true", help="skip nefii's albedo-over-time re-run")
    ap.add_argument("--force", action="store_true", help="refit the peer and re-run nefii's curve even if cached")
    ap.add_argument("--set", dest="extra", action="append", default=[], metavar="KEY=VALUE",
                    help="nefii config override for its fits and curve (as benchmarks.quality --set)")
    for f in dataclasses.fields(PeerConfig):
        if f.name != "threads":
            ap.add_argument(f"--peer-{f.name.replace('_', '-')}", dest=f"peer_{f.name}", type=type(f.default),
                            default=f.default)
    ap.add_argument("--worker", choices=("peer", "curve"), help=argparse.SUPPRESS)
    ap.add_argument("--data", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--max-steps", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cfg = PeerConfig(**{f.name: getattr(args, f"peer_{f.name}") for f in dataclasses.fields(PeerConfig)
                        if f.name != "threads"}, threads=args.threads)

    if args.worker == "peer":
        peer_worker(args.data, args.out, args.budget_s, cfg, args.eval_spp, args.checks, args.max_steps)
        return
    if args.worker == "curve":
        curve_worker(args.data, args.out, args.threads, args.curve_every, args.extra, args.max_steps)
        return

    t_start = time.time()
    datas = {s: common.scene(s, args.res, args.views, args.test_views) for s in args.scenes}
    pool = ThreadPoolExecutor(args.jobs)
    if not args.skip_nefii:  # full first: its fit time is the peer's budget
        list(pool.map(lambda s: quality.run_one(datas[s], s, "full", args.extra, args.threads, args.eval_spp),
                      args.scenes))
    jobs, later = [], []  # the peers first, then the nefii baselines and curves
    if not args.skip_nefii:
        later += [(quality.run_one, (datas[s], s, c, args.extra, args.threads, args.eval_spp))
                  for s in args.scenes for c in NEFII_CONFIGS[1:]]
    peer_flags = [x for f in dataclasses.fields(PeerConfig) if f.name != "threads"
                  for x in (f"--peer-{f.name.replace('_', '-')}", str(getattr(cfg, f.name)))]
    for s in args.scenes:
        out = peer_dir(s)
        budget = budget_for(s, args.budget_s)
        if args.force or not peer_is_current(out, datas[s], budget, cfg, args.eval_spp):
            cmd = ["--worker", "peer", "--data", str(datas[s]), "--out", str(out), "--budget-s", str(budget),
                   "--threads", str(args.threads), "--eval-spp", str(args.eval_spp), "--checks", str(args.checks),
                   *peer_flags]
            jobs.append((run_worker, (cmd, f"peer {s}", args.threads)))
        if not args.no_curve and (args.force or not curve_is_current(out, datas[s], args.extra)):
            cmd = ["--worker", "curve", "--data", str(datas[s]), "--out", str(out), "--threads", str(args.threads),
                   "--curve-every", str(args.curve_every), *[x for kv in args.extra for x in ("--set", kv)]]
            if args.curve_max_steps is not None:
                cmd += ["--max-steps", str(args.curve_max_steps)]
            later.append((run_worker, (cmd, f"nefii curve {s}", args.threads)))
    list(pool.map(lambda j: j[0](*j[1]), jobs + later))
    pool.shutdown()
    write_report(args.scenes, command_line(args), time.time() - t_start)


if __name__ == "__main__":
    main()
