"""Issue 7: nefii side by side with a peer, Mitsuba 3 inverse rendering, on the built-in scenes.

    python benchmarks/peers/mitsuba_inverse.py [--scenes bowl cup] [--budget-s S] [--threads 1]
        [--res 128 --views 64] [--jobs 2] [--skip-nefii] [--no-curve] [--force] [--set KEY=VALUE]
        [--peer-lr-env 0.2 ...]  (every PeerConfig field has a --peer-* flag)

Per scene, on the same data, mesh, test views and eval code:

* nefii ``full``, ``light_envmap`` (the env-map-grid baseline) and ``physg`` (``visibility=off,
  indirect=off``, the PhySG-style baseline): ``benchmarks/quality.py``'s runs, reused when complete
  and fitted (``cpu`` preset, ``--threads`` each) when missing, unless ``--skip-nefii``;
* the Mitsuba peer (``mitsuba_peer``): ``prb`` on ``llvm_ad_rgb`` optimising principled textures
  over the ``nefii export`` xatlas atlas and an env map, for the wall-clock budget of nefii full's
  fit on that scene (or ``--budget-s``), then scored by ``peer_eval``; cached in
  ``benchmarks/.cache/peers/<scene>/`` (textures, env map, curve.csv, result.json, eval/);
* nefii's albedo PSNR over fitting time (``nefii_curve``: the full fit re-run with snapshots),
  ``benchmarks/.cache/peers/<scene>/nefii_curve.csv``, unless ``--no-curve``.

Writes ``benchmarks/results/peers.md`` and ``peers.png`` from whatever is cached. Each fit runs in
its own process (``--worker``), so its peak RSS is its own; ``--jobs`` of them at a time.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata as md
import json
import os
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import common  # noqa: E402
import quality  # noqa: E402
from mitsuba_peer import PeerConfig  # noqa: E402

SCENES = ("bowl", "cup", "leaning", "corner")
NEFII_CONFIGS = ("full", "light_envmap", "physg")


def peer_dir(name: str) -> Path:
    return common.CACHE / "peers" / name


def gib(maxrss_kib: int) -> float:
    return maxrss_kib / 2**20


# ---------------------------------------------------------------- workers (one process each)

def peer_worker(data: Path, out: Path, budget_s: float, cfg: PeerConfig, eval_spp: int, checks: int,
                max_steps: int | None = None) -> dict:
    """Fit the peer on ``data`` for ``budget_s`` seconds of steps, score it, write ``out``."""
    import numpy as np
    import torch

    from nefii.data import load_scene
    from nefii.export.unwrap import unwrap
    from nefii.geometry import MeshGeometry
    from nefii.io.atomic import write_text_atomic
    from nefii.io.exr import write_exr
    from nefii.io.images import write_png

    from mitsuba_peer import MeshData, MitsubaPeer, camera_rig, config_record, premultiplied_images
    from peer_eval import evaluate
    from views import cast_test_views, hit_uv, material_scores, scatter, textures_at_views

    torch.set_num_threads(cfg.threads)
    t0 = time.perf_counter()
    train, test = load_scene(data, "train"), load_scene(data, "test")
    geometry = MeshGeometry.from_file(train.mesh_path, threads=cfg.threads)  # nefii's mesh and normals
    atlas = unwrap(geometry.vertices, geometry.faces, cfg.texture_size)
    mesh = MeshData(geometry.vertices.astype(np.float64), geometry.faces, geometry.vertex_normals, atlas)
    peer = MitsubaPeer(mesh, camera_rig(train), premultiplied_images(train), cfg)
    views = cast_test_views(test, geometry)
    uvs = [hit_uv(h, geometry.vertices, geometry.faces, atlas) for h in views.hits]
    setup_s = time.perf_counter() - t0

    checked: dict[int, dict] = {}

    def check(p: MitsubaPeer, fit_s: float) -> None:
        base, rough = p.textures()
        checked[p.step] = material_scores(views, *textures_at_views(views, uvs, base, rough))

    every = budget_s / checks if max_steps is None else float("inf")
    loss_before = peer.mean_image_loss()
    fit = peer.fit(budget_s, max_steps, check, every)
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
        "config": config_record(cfg), "eval_spp": eval_spp, "max_steps": max_steps,
        "loss_all_training_views": {"before": loss_before, "after": loss_after, "spp": 16},
        "mesh": {"vertices": len(geometry.vertices), "triangles": len(geometry.faces),
                 "atlas_vertices": len(atlas.uv)},
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

    from nefii_curve import run_curve, write_curve_csv

    points, cfg, fit_s = run_curve(data, threads, every, overrides, max_steps=max_steps)
    write_curve_csv(out / "nefii_curve.csv", points)
    write_text_atomic(out / "nefii_curve.json", json.dumps({
        "data": str(data), "preset": cfg.preset, "threads": threads, "steps": points[-1].step, "fit_s": fit_s,
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

def _subprocess(args: list[str], what: str, threads: int) -> None:
    env = dict(os.environ, OMP_NUM_THREADS=str(max(threads, 1)))
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], capture_output=True, text=True,
                          env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{proc.stderr[-3000:]}")


def peer_is_current(out: Path, data: Path, budget_s: float, cfg: PeerConfig, eval_spp: int) -> bool:
    f = out / "result.json"
    if not f.is_file():
        return False
    res = json.loads(f.read_text())
    same = {k: v for k, v in res["config"].items() if k in dataclasses.asdict(cfg)} == dataclasses.asdict(cfg)
    return same and abs(res["budget_s"] - budget_s) < 1.0 and res["eval_spp"] == eval_spp and res["data"] == str(data)


def curve_is_current(out: Path, data: Path, extra: list[str]) -> bool:
    f = out / "nefii_curve.json"
    if not (f.is_file() and (out / "nefii_curve.csv").is_file()):
        return False
    rec = json.loads(f.read_text())
    return rec["data"] == str(data) and rec.get("sets", []) == extra


def budget_for(name: str, override: float | None) -> float:
    if override is not None:
        return override
    row = quality.read_row(name, "full")
    if row is None:
        raise SystemExit(f"peers: no completed nefii full run for {name} to take the budget from; run without "
                         "--skip-nefii or give --budget-s")
    return float(row["fit_s"])


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
                    help="nefii config override for its fits and curve (as quality.py --set)")
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
            jobs.append((_subprocess, (cmd, f"peer {s}", args.threads)))
        if not args.no_curve and (args.force or not curve_is_current(out, datas[s], args.extra)):
            cmd = ["--worker", "curve", "--data", str(datas[s]), "--out", str(out), "--threads", str(args.threads),
                   "--curve-every", str(args.curve_every), *[x for kv in args.extra for x in ("--set", kv)]]
            if args.curve_max_steps is not None:
                cmd += ["--max-steps", str(args.curve_max_steps)]
            later.append((_subprocess, (cmd, f"nefii curve {s}", args.threads)))
    list(pool.map(lambda j: j[0](*j[1]), jobs + later))
    pool.shutdown()
    write_results(args, time.time() - t_start)


def write_results(args: argparse.Namespace, elapsed_s: float) -> None:
    from report import NEFII_ROWS, PEER, curve_sentence, nefii_row, peer_rows, plot, table, verdict

    order = list(dict.fromkeys([*SCENES, *args.scenes]))
    per_scene, curves, finals = {}, {}, {}
    for s in order:
        rows = [r for c, label in NEFII_ROWS if (r := nefii_row(quality.read_row, s, c, label)) is not None]
        rows += peer_rows(peer_dir(s) / "result.json")
        if any(r.system == PEER for r in rows):
            per_scene[s] = rows
            curves[s] = {"nefii full": peer_dir(s) / "nefii_curve.csv", PEER: peer_dir(s) / "curve.csv"}
            finals[s] = {r.system: r.values.get("albedo_psnr") for r in rows}
    plotted = plot(common.RESULTS / "peers.png", curves, finals)
    cmd = "python benchmarks/peers/mitsuba_inverse.py --scenes " + " ".join(args.scenes)
    if os.environ.get("NEFII_BENCH_CACHE"):
        cmd = f"NEFII_BENCH_CACHE={os.environ['NEFII_BENCH_CACHE']} " + cmd
    if args.budget_s is not None:
        cmd += f" --budget-s {args.budget_s:g}"
    if args.threads != 1:
        cmd += f" --threads {args.threads}"
    if (args.res, args.views, args.test_views) != (128, 64, 8):
        cmd += f" --res {args.res} --views {args.views} --test-views {args.test_views}"
    cmd += "".join(f" --set {kv}" for kv in args.extra)
    peer_cfg = None
    for s in per_scene:
        f = peer_dir(s) / "result.json"
        peer_cfg = json.loads(f.read_text())
        break
    lines = [f"# peers: nefii and Mitsuba 3 inverse rendering ({common.stamp()})", "",
             f"Machine: {common.machine()}; " + ", ".join(f"{k} {v}" for k, v in versions().items()) + ".",
             f"Scenes {args.res}x{args.res}, {args.views} training views, {args.test_views} test views. "
             f"Reproduce (from the repository root, fits cached in benchmarks/.cache): `{cmd}`. "
             f"This invocation: {elapsed_s / 60:.1f} min; current code {common.code_version()}.", "",
             "Every row is scored by nefii's own eval code (`nefii.evaluate.table1`, masked block: object pixels, "
             "albedo aligned per view and channel by median(gt/pred)) on the same test views, pixel-centre rays "
             "against the same mesh. nefii rows: `benchmarks/quality.py` runs (`cpu` preset; env-map grid = "
             "`light.kind=envmap`; PhySG-style = `visibility=off indirect=off`), eval at "
             f"{args.eval_spp} spp. The peer: Mitsuba's `prb` integrator (llvm_ad_rgb) optimising a principled "
             "BSDF's base-colour and roughness textures over the xatlas atlas of `nefii export` and a "
             "low-resolution `envmap` (log radiance, total-variation prior), with Adam, for the wall-clock "
             "time of nefii full's fit on the same scene; its albedo/roughness are its textures read at the "
             "test hits, its novel views Mitsuba renders of the recovered scene "
             f"(depth 12, {args.eval_spp} spp). Wall time: fitting only (setup and curve evaluations off the "
             "clock); peak GiB: peak RSS of the fitting process. Specular PSNR: the specular lobe's layer.", ""]
    if peer_cfg is not None:
        c = peer_cfg["config"]
        lines += [f"Peer settings: {c['texture_size']}^2 textures, {c['env_height']}x{2 * c['env_height']} env map, "
                  f"{c['views_per_step']} view(s) x {c['spp']} spp per step, prb max_depth {c['max_depth']}, "
                  f"{c['loss']} loss, Adam lr {c['lr_texture']} (textures) / {c['lr_env']} (log env), decaying "
                  f"to x{c['lr_decay']} over the budget, priors: env TV {c['env_tv']}, texture TV "
                  f"{c['texture_tv']}; {c['threads']} thread(s). These were picked by a handful of 60-second "
                  "trials on bowl (loss kind, learning rates, texture prior), looking at test albedo PSNR — "
                  "as nefii's `cpu` preset was tuned on these scenes.", ""]
    for s, rows in per_scene.items():
        lines += [f"## {s}", "", *table(rows), ""]
    lines += ["## Albedo PSNR against fitting time", ""]
    if plotted:
        lines += ["![albedo PSNR against time](peers.png)", "",
                  "nefii's curve is the full fit re-run in process with snapshots (`nefii_curve.py`: same "
                  "recipe, seed and code, so its last point is the table's nefii-full albedo PSNR when the "
                  "code has not changed; it writes no checkpoints or previews, and its time axis is its own "
                  "measured fitting time); the peer's curve is its own run. Both are evaluated off the clock.",
                  ""]
        lines += [f"- {t}" for s in per_scene if (t := curve_sentence(
            s, peer_dir(s) / "curve.csv", peer_dir(s) / "nefii_curve.csv"))]
        lines.append("")
    lines += ["## Where each system wins (generated from the numbers above)", ""]
    lines += [verdict(s, rows) for s, rows in per_scene.items()]
    missing = [f"{s}/{label}" for s in args.scenes for c, label in NEFII_ROWS if quality.read_row(s, c) is None]
    missing += [f"{s}/{PEER}" for s in args.scenes if not (peer_dir(s) / "result.json").is_file()]
    if missing:
        lines += ["", "Not run yet: " + ", ".join(missing) + "."]
    text = "\n".join(lines) + "\n"
    print(text)
    common.RESULTS.mkdir(exist_ok=True)
    (common.RESULTS / "peers.md").write_text(text)


if __name__ == "__main__":
    main()
