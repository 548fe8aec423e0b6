"""The ``gpu`` preset at the paper's scale: a 512 x 512, 100-view built-in scene fitted on one GPU.

Two verbs, because the fit needs the GPU and the scoring does not:

``python -m benchmarks.gpu fit [--data SCENE] --out RUN``
    fits the scene (default: the bowl at 512 x 512, 100 training views, synthesised once into the cache) with
    ``--preset gpu`` on the GPU and records the whole command's wall time in ``RUN/benchmark_wall.json`` (the
    fit's own ``fit_stats.json`` holds its steps/s, set-up time and peak GPU memory).
``python -m benchmarks.gpu table --gpu RUN... --cpu RUN... [--data SCENE]``
    scores the runs with ``nefii eval`` (where not yet scored) on the same scene and writes
    ``results/gpu.md``: device, time, memory and quality of the ``gpu`` preset's fits against the ``cpu``
    preset's fits of the same data (one run per seed).
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


def fit(data: Path, out: Path, device: str, resume: bool, limit_s: float | None) -> int:
    start = time.time()
    cmd = [sys.executable, "-m", "nefii.cli.main", "fit", str(data), "--out", str(out), "--preset", "gpu",
           "--device", device, "--quiet", *(["--resume"] if resume else [])]
    try:
        rc = subprocess.run(cmd, timeout=limit_s).returncode
    except subprocess.TimeoutExpired:   # killed; its checkpoints let `fit --resume` go on
        rc = 124
    finally:    # also when a time limit stops it: a resumed fit adds its sessions' times
        wall = time.time() - start
        record = out / "benchmark_wall.json"
        before = json.loads(record.read_text()) if resume and record.exists() else {"wall_s": 0.0, "sessions": 0}
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


def table(gpu_runs: list[Path], cpu_runs: list[Path], data: Path, note: str = "") -> None:
    setting = json.loads((data / "scene.json").read_text())["settings"]
    rows, means = [], {}
    for preset, runs in (("gpu", gpu_runs), ("cpu", cpu_runs)):
        got = []
        for run in runs:
            stats = json.loads((run / "fit_stats.json").read_text())
            cfg = json.loads((run / "config.json").read_text())
            wall_file = run / "benchmark_wall.json"
            wall = (json.loads(wall_file.read_text())["wall_s"] if wall_file.exists()
                    else stats["setup_s"] + stats["wall_s_this_session"])
            m = scored(run, data)
            got.append((wall, m))
            gpu_mem = f"{stats['peak_gpu_gib']:.2f} GiB" if "peak_gpu_gib" in stats else "-"
            threads = f"{stats['threads']} thread" + ("s" if stats["threads"] != 1 else "")
            rows.append(f"| `{preset}` | {cfg['seed']} | {stats['device']}, {threads} | "
                        f"{cfg['batch_pixels']} x {cfg['num_samples']} | "
                        f"{wall / 60:.1f} (set-up {stats['setup_s']:.0f} s) | "
                        f"{stats['steps_per_s']:.2f} | {gpu_mem} | {stats['peak_rss_gib']:.2f} GiB | "
                        f"{m['albedo_psnr']:.2f} | {m['roughness_mse']:.4f} | {m['specular_psnr']:.2f} | "
                        f"{m['rgb_psnr']:.2f} |")
        means[preset] = {k: sum(m[k] for _, m in got) / len(got) for k in ("albedo_psnr", "roughness_mse",
                                                                             "specular_psnr", "rgb_psnr")}
        means[preset]["wall_max"] = max(w for w, _ in got)
    g, c = means["gpu"], means["cpu"]
    lines = [f"# gpu preset ({stamp()})", "",
             f"Scene: {setting['scene']}, {setting['views']} training views {setting['res']}x{setting['res']}, "
             f"{setting['test_views']} test views; ground-truth mesh, masked test views, "
             f"`nefii eval --spp {EVAL_SPP}`. "
             "Made by `python -m benchmarks.gpu table` from the runs below.", "",
             "| preset | seed | device of the fit | pixels x N a step | `nefii fit` min | steps/s | peak GPU memory | "
             "peak RSS | albedo PSNR | roughness MSE | specular PSNR | RGB PSNR |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|", *rows, "", *([note, ""] if note else []),
             f"Mean of the seeds, `gpu` against `cpu`: albedo {g['albedo_psnr']:.2f} / {c['albedo_psnr']:.2f} dB, "
             f"roughness MSE {g['roughness_mse']:.4f} / {c['roughness_mse']:.4f}, specular {g['specular_psnr']:.2f} / "
             f"{c['specular_psnr']:.2f} dB, RGB {g['rgb_psnr']:.2f} / {c['rgb_psnr']:.2f} dB.", "",
             f"Targets: the `gpu` fit within 20 min ({'met' if g['wall_max'] <= 20 * 60 else 'NOT met'}: slowest "
             f"{g['wall_max'] / 60:.1f} min on the device above), quality at least the `cpu` preset's (albedo "
             f"{'met' if g['albedo_psnr'] >= c['albedo_psnr'] else 'NOT met'}, roughness "
             f"{'met' if g['roughness_mse'] <= c['roughness_mse'] else 'NOT met'})."]
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
    t.add_argument("--gpu", type=Path, nargs="+", required=True, help="runs of the gpu preset (one per seed)")
    t.add_argument("--cpu", type=Path, nargs="+", required=True, help="runs of the cpu preset on the same data")
    t.add_argument("--data", type=Path, default=None)
    t.add_argument("--note", default="", help="a paragraph on how the runs ran (machines, what shared them)")
    args = p.parse_args(argv)
    data = args.data if args.data is not None else scene(*SCENE)
    if args.verb == "fit":
        return fit(data, args.out, args.device, args.resume, args.limit_s)
    table(args.gpu, args.cpu, data, args.note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
