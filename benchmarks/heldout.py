"""Issue 27's targets on scenes no setting was tried on: each built-in object under another built-in light.

    python -m benchmarks.heldout [--scenes bowl@studio ...] [--seeds 0 1] [--jobs 2] [--set key=value ...]

The four built-in scenes are where the fit's settings were chosen; a user's scene is another object under
another light. Each object is rendered under an environment it was never fitted under (``nefii synth OBJECT
--env ENV``: the same views and materials, another light), fitted with ``nefii fit`` (``cpu`` preset) and
scored by ``nefii eval`` (masked, albedo aligned per view and channel), at every seed. Runs live in
``benchmarks/.cache/runs/heldout`` and are reused when complete. Writes ``benchmarks/results/heldout.md``: every
run, the seeds' means, and issue 27's albedo and roughness targets against the means.
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .common import (CACHE, code_version, fit_and_eval, fit_arguments, fit_digest, fit_threads, machine, note_lines,
                     run_figures, scene, set_flags, stamp, write_results)

SWAPS = ("bowl@studio", "leaning@overcast", "cup@noon", "corner@sunset")
"""each object under a light of another scene: hard sun on the soft-lit objects, soft light on the sunlit ones"""


def run_dir(name: str, seed: int, extra: Sequence[str] = ()) -> Path:
    """Named by the scene, the seed and a digest of the fit settings (:func:`benchmarks.common.fit_digest`)."""
    return CACHE / "runs" / "heldout" / f"{name}_s{seed}_{fit_digest([f'seed={seed}', *extra])}"


def run_one(data: Path, name: str, seed: int, extra: list[str], threads: int, eval_spp: int) -> None:
    """``nefii fit`` then ``nefii eval`` of one scene at one seed, unless done."""
    fit_and_eval(data, run_dir(name, seed, extra), set_flags([f"seed={seed}", *extra], threads), eval_spp,
                 f"{name} seed {seed}", extra)


def table(names: list[str], seeds: list[int], extra: Sequence[str] = ()) -> list[str]:
    """Per-run rows, then per-scene means with issue 27's targets (albedo >= 26 dB, roughness MSE <= 0.02)."""
    rows = ["| scene | seed | albedo PSNR | roughness MSE | specular PSNR | rgb PSNR | fit min | thr | code |",
            "|---|---|---|---|---|---|---|---|---|"]
    means = ["| scene | seeds | albedo PSNR | roughness MSE | albedo >= 26 dB | roughness <= 0.02 |", "|---|---|---|---|---|---|"]
    for name in names:
        runs = {s: run_figures(run_dir(name, s, extra)) for s in seeds}
        for s, r in runs.items():
            if r is not None:
                rows.append(f"| {name} | {s} | {r['albedo_psnr']:.2f} | {r['roughness_mse']:.4f} | "
                            f"{r['specular_psnr']:.2f} | {r['rgb_psnr']:.2f} | {r['fit_s'] / 60:.1f}{'*' if r['resumed'] else ''} | {r['threads']} | "
                            f"{r['code']} |")
        done = [r for r in runs.values() if r is not None]
        if done:
            a = sum(r["albedo_psnr"] for r in done) / len(done)
            m = sum(r["roughness_mse"] for r in done) / len(done)
            means.append(f"| {name} | {len(done)} | {a:.2f} | {m:.4f} | {'met' if a >= 26 else 'NOT met'} | "
                         f"{'met' if m <= 0.02 else 'NOT met'} |")
    return [*rows, "", *means]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SWAPS), help="OBJECT@ENV (default: %(default)s)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    fit_arguments(ap)
    ap.add_argument("--note", default="", help="a paragraph printed under the machine line (how the rows were "
                    "made, when that is not this invocation); @FILE reads it from FILE")
    args = ap.parse_args()
    bad = [n for n in args.scenes if "@" not in n]
    if bad:
        ap.error(f"--scenes: {', '.join(bad)} is not OBJECT@ENV (an object under another light)")
    datas = {n: scene(n, args.res, args.views, args.test_views) for n in args.scenes}
    threads = fit_threads(args.threads, args.jobs)
    jobs = [(datas[n], n, s) for n in args.scenes for s in args.seeds]
    t0 = time.time()
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda j: run_one(*j, args.extra, threads, args.eval_spp), jobs))
    write_results("heldout.md", [
        f"# heldout ({stamp()})", "",
        f"Machine: {machine()}. Each built-in object under another built-in light (`nefii synth OBJECT --env ENV`), "
        f"{args.res}x{args.res}, {args.views} training views, {args.test_views} test views; `cpu` preset"
        f"{' + ' + ' '.join(args.extra) if args.extra else ''}; eval at {args.eval_spp} spp, masked, albedo aligned "
        f"per view and channel. This invocation: {len(jobs)} runs in {(time.time() - t0) / 60:.1f} min (cached runs "
        f"reused); current code {code_version()}.", "", *note_lines(args.note),
        *table(args.scenes, args.seeds, args.extra)])


if __name__ == "__main__":
    main()
