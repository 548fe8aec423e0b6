"""How long ``nefii eval`` takes at its default settings, and how noisy its figures are.

    python -m benchmarks.eval_speed [--run RUN] [--data DIR] [--views 16]

Two evals of the same fitted run, each ``nefii eval RUN --data DATA --seed S --threads 0`` (default spp,
all cores: what a default ``nefii fit`` saves and eval then uses) in a fresh process on a copy of the run,
timed from process start to exit (what a user waits). The scene is the bowl at
128 x 128 with ``--views`` test views (synthesised once; Mitsuba needed the first time); the run is the
quality benchmark's bowl fit if it exists, else one ``cpu``-preset fit made here. The Monte Carlo noise of
the figures is stated twice: the difference of each metric between the two evals (seeds 0 and 1), and the
PSNR of one eval's rendered colour against the other's. Writes ``benchmarks/results/eval_speed.md``. Target
(issue 28): 16 views at 128 x 128 within 2 min on 2 cores. Run it on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import CACHE, REPO, code_version, machine, scene, stamp, write_results
from .quality import run_dir

TARGET_S = 120.0
KEYS = ("albedo_psnr", "roughness_mse", "specular_psnr", "rgb_psnr")


def fitted_run(data: Path) -> Path:
    """The quality benchmark's bowl fit, or a ``cpu``-preset fit of ``data`` made once into the cache."""
    quality = run_dir("bowl", "full")
    if (quality / "model.pt").exists():
        return quality
    run = CACHE / "runs" / "eval_speed_bowl"
    if not (run / "model.pt").exists():
        print(f"fitting {data.name} once for the benchmark (cpu preset) into {run}", flush=True)
        subprocess.run([sys.executable, "-m", "nefii.cli.main", "fit", str(data), "--out", str(run), "--quiet"],
                       cwd=REPO, check=True)
    return run


def timed_eval(run: Path, data: Path, seed: int, work: Path) -> tuple[float, Path]:
    """Copy ``run``'s fitted state into ``work`` and time one ``nefii eval`` of it; returns (seconds, eval dir)."""
    copy = work / f"run_seed{seed}"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval", "checkpoints", "previews", "tensorboard"))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "nefii.cli.main", "eval", str(copy), "--data", str(data), "--seed",
                    str(seed), "--threads", "0", "--quiet"], cwd=REPO, check=True)
    return time.perf_counter() - t0, copy / "eval"


def render_psnr(a: Path, b: Path, indices: list[int]) -> float:
    """PSNR of the rendered colour of eval ``a`` against eval ``b`` over the views ``indices`` (linear, peak 1)."""
    from nefii.evaluate.metrics import psnr  # noqa: PLC0415
    from nefii.io.exr import read_exr  # noqa: PLC0415

    def stack(folder: Path) -> np.ndarray:
        return np.stack([read_exr(folder / f"{i}_rgb.exr")[..., :3] for i in indices])

    return psnr(stack(a), stack(b))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=None, help="fitted run (default: the bowl, see above)")
    ap.add_argument("--data", type=Path, default=None, help="scene with the test views (default: the bowl)")
    ap.add_argument("--views", type=int, default=16, help="test views of the default scene")
    args = ap.parse_args(argv)
    data = args.data or scene("bowl", test_views=args.views)
    run = args.run or fitted_run(scene("bowl"))
    with tempfile.TemporaryDirectory(prefix="nefii_eval_speed_") as tmp:
        times, outs = [], []
        for seed in (0, 1):
            s, out = timed_eval(run, data, seed, Path(tmp))
            times.append(s)
            outs.append(out)
            print(f"eval seed {seed}: {s:.1f} s", flush=True)
        metrics = [json.loads((o / "metrics.json").read_text()) for o in outs]
        indices = [view["index"] for view in metrics[0]["views"]]
        views = len(indices)
        noise = render_psnr(outs[0], outs[1], indices)
    m0, m1 = metrics[0]["masked"], metrics[1]["masked"]
    worst = max(times)
    lines = [f"# eval_speed ({stamp()}, code {code_version()})", "", f"Machine: {machine()}.",
             f"Made by `python -m benchmarks.eval_speed` on `{data.name}` ({views} test views) with the fitted run "
             f"`{run.name}`: two `nefii eval` runs at the default settings (seeds 0 and 1, `--threads 0`: all cores, "
             "as a default `nefii fit` saves it), each a fresh process timed from start to exit.", "",
             "| eval | wall s | s per view | target |", "|---|---|---|---|"]
    for seed, s in enumerate(times):
        lines.append(f"| seed {seed} | {s:.1f} | {s / views:.2f} | <= {TARGET_S:.0f} s: "
                     f"{'met' if s <= TARGET_S else 'not met'} |")
    lines += ["", "Monte Carlo noise of the figures (masked test views): the same run evaluated with two seeds.", "",
              "| metric | seed 0 | seed 1 | difference |", "|---|---|---|---|"]
    for k in KEYS:
        fmt = ".4f" if k.endswith("mse") else ".2f"
        lines.append(f"| {k} | {m0[k]:{fmt}} | {m1[k]:{fmt}} | {abs(m0[k] - m1[k]):{fmt}} |")
    lines += ["", f"PSNR of seed 0's rendered colour against seed 1's over all {views} views: {noise:.1f} dB.",
              "", f"Slowest eval {worst:.1f} s against the {TARGET_S:.0f} s target: "
              f"{'met' if worst <= TARGET_S else 'not met'}."]
    write_results("eval_speed.md", lines)


if __name__ == "__main__":
    main()
