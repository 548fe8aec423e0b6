"""The ``gpu`` preset at the paper's scale: a 512 x 512, 100-view built-in scene fitted on one GPU.

Two verbs, because the fit needs the GPU and the scoring does not:

``python -m benchmarks.gpu fit [--data SCENE] --out RUN``
    fits the scene (default: the bowl at 512 x 512, 100 training views, synthesised once into the cache) with
    ``--preset gpu`` on the GPU and records the whole command's wall time in ``RUN/benchmark_wall.json`` (the
    fit's own ``fit_stats.json`` holds its steps/s, set-up time and peak GPU memory).
``python -m benchmarks.gpu table GPU_RUN CPU_RUN [--data SCENE]``
    scores both runs with ``nefii eval`` (where not yet scored) on the same scene and writes
    ``results/gpu.md``: device, time, memory and quality of the ``gpu`` preset's fit against the ``cpu``
    preset's fit of the same data.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from .common import scene, stamp, write_results

SCENE = ("bowl", 512, 100, 8, 64)
"""name, resolution, training views, test views, spp of the scene the issue names"""
EVAL_SPP = 64


def fit(data: Path, out: Path, device: str, extra: list[str], limit_s: float | None) -> int:
    start = time.time()
    cmd = [sys.executable, "-m", "nefii.cli.main", "fit", str(data), "--out", str(out), "--preset", "gpu",
           "--device", device, "--quiet", *extra]
    try:
        rc = subprocess.run(cmd, timeout=limit_s).returncode
    except subprocess.TimeoutExpired:   # killed; its checkpoints let `fit --resume` go on
        rc = 124
    finally:    # also when a time limit stops it: a resumed fit adds its sessions' times
        wall = time.time() - start
        record = out / "benchmark_wall.json"
        before = json.loads(record.read_text()) if extra and record.exists() else {"wall_s": 0.0, "sessions": 0}
        if out.is_dir():
            record.write_text(json.dumps({"wall_s": before["wall_s"] + wall, "sessions": before["sessions"] + 1,
                                          "command": cmd[2:]}, indent=2) + "\n")
    print(f"benchmarks.gpu: fit exited {rc} after {wall:.1f} s")
    return rc


def scored(run: Path, data: Path) -> dict:
    metrics = run / "eval" / "metrics.json"
    if not metrics.exists():
        subprocess.run([sys.executable, "-m", "nefii.cli.main", "eval", str(run), "--data", str(data),
                        "--spp", str(EVAL_SPP), "--quiet"], check=True)
    return json.loads(metrics.read_text())["masked"]


def table(gpu_run: Path, cpu_run: Path, data: Path) -> None:
    stats = {k: json.loads((r / "fit_stats.json").read_text()) for k, r in (("gpu", gpu_run), ("cpu", cpu_run))}
    walls = {k: (json.loads((r / "benchmark_wall.json").read_text())["wall_s"]
                 if (r / "benchmark_wall.json").exists() else None) for k, r in (("gpu", gpu_run), ("cpu", cpu_run))}
    configs = {k: json.loads((r / "config.json").read_text()) for k, r in (("gpu", gpu_run), ("cpu", cpu_run))}
    metrics = {"gpu": scored(gpu_run, data), "cpu": scored(cpu_run, data)}
    setting = json.loads((data / "scene.json").read_text())["settings"]

    def minutes(k: str) -> str:
        s = stats[k]
        total = walls[k] if walls[k] is not None else s["setup_s"] + s["wall_s_this_session"]
        return f"{total / 60:.1f} min (set-up {s['setup_s']:.0f} s, steps {s['wall_s_this_session'] / 60:.1f} min)"

    def row(name: str, f) -> str:
        return f"| {name} | {f('gpu')} | {f('cpu')} |"

    ok = walls["gpu"] is not None and walls["gpu"] <= 20 * 60
    lines = [f"# gpu preset ({stamp()})", "",
             f"Scene: {setting['scene']}, {setting['views']} training views {setting['res']}x{setting['res']}, "
             f"{setting['test_views']} test views; ground-truth mesh, masked; eval at {EVAL_SPP} spp.", "",
             "| figure | `gpu` preset | `cpu` preset |", "|---|---|---|",
             row("device", lambda k: stats[k]["device"] + f", {stats[k]['threads']} CPU threads"),
             row("steps x pixels x N", lambda k: f"{configs[k]['steps']} x {configs[k]['batch_pixels']} x "
                                                 f"{configs[k]['num_samples']}"),
             row("wall time of `nefii fit`", minutes),
             row("steps/s", lambda k: f"{stats[k]['steps_per_s']:.2f}"),
             row("peak GPU memory", lambda k: f"{stats[k]['peak_gpu_gib']:.2f} GiB" if "peak_gpu_gib" in stats[k]
                 else "n/a"),
             row("peak resident memory", lambda k: f"{stats[k]['peak_rss_gib']:.2f} GiB"),
             row("albedo PSNR", lambda k: f"{metrics[k]['albedo_psnr']:.2f} dB"),
             row("roughness MSE", lambda k: f"{metrics[k]['roughness_mse']:.4f}"),
             row("specular PSNR", lambda k: f"{metrics[k]['specular_psnr']:.2f} dB"),
             row("novel-view RGB PSNR", lambda k: f"{metrics[k]['rgb_psnr']:.2f} dB"),
             "",
             f"Target: the `gpu` fit within 20 min on one H100 ({'met' if ok else 'NOT met'} on the device above), "
             "quality at least the `cpu` preset's: albedo "
             f"{'met' if metrics['gpu']['albedo_psnr'] >= metrics['cpu']['albedo_psnr'] else 'NOT met'}, roughness "
             f"{'met' if metrics['gpu']['roughness_mse'] <= metrics['cpu']['roughness_mse'] else 'NOT met'}."]
    write_results("gpu.md", lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.gpu", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="verb", required=True)
    f = sub.add_parser("fit")
    f.add_argument("--data", type=Path, default=None)
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--device", default="cuda")
    f.add_argument("--resume", action="store_true")
    f.add_argument("--limit-s", type=float, default=None, help="stop the fit after this many seconds")
    t = sub.add_parser("table")
    t.add_argument("gpu_run", type=Path)
    t.add_argument("cpu_run", type=Path)
    t.add_argument("--data", type=Path, default=None)
    args = p.parse_args(argv)
    data = args.data if args.data is not None else scene(*SCENE)
    if args.verb == "fit":
        return fit(data, args.out, args.device, ["--resume"] if args.resume else [], args.limit_s)
    table(args.gpu_run, args.cpu_run, data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
