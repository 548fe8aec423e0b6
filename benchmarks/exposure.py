"""Does a fit depend on the images' exposure? Built-in scenes with every colour image times a factor.

    python -m benchmarks.exposure [--scenes corner leaning] [--factors 0.125 1 8] [--seeds 0] [--jobs 2]

A user's images may be darker or brighter than the built-in renders (a dim room, HDR stored in other units); the
materials should not care, since the albedo and the light's scale are one unknown. Each scene is copied with its
training and test images (and the test views' diffuse and specular layers) times each factor (``factor`` 1: the
scene itself), fitted with ``nefii fit`` (``cpu`` preset) and scored by ``nefii eval`` (masked, albedo aligned
per view and channel). Runs live in ``benchmarks/.cache/runs/exposure`` and are reused when complete. Writes
``benchmarks/results/exposure.md``.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .common import (CACHE, code_version, fit_and_eval, fit_arguments, fit_digest, fit_threads, machine, note_lines,
                     run_figures,
                     scene, set_flags, stamp, write_results)

COLOUR = re.compile(r"r_\d+(_diffuse|_specular)?\.exr")
"""the files of a nefii-layout scene that hold radiance (the other layers are ratios, masks or geometry)"""


def exposed_scene(clean: Path, factor: float) -> Path:
    """``clean`` with its colour images times ``factor``, made once beside it (the rest linked)."""
    if factor == 1.0:
        return clean
    from nefii.io.exr import read_exr, write_exr  # noqa: PLC0415

    out = clean.with_name(f"{clean.name}_x{factor:g}")
    if (out / "transforms_train.json").exists():
        return out
    tmp = out.with_name(f".{out.name}.partial")                  # renamed onto ``out`` when whole
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    for p in clean.iterdir():
        if p.name not in ("train", "test"):
            os.symlink(p.resolve(), tmp / p.name)
            continue
        (tmp / p.name).mkdir()
        for f in p.iterdir():
            if COLOUR.fullmatch(f.name):
                img = read_exr(f)
                img[..., :3] *= factor                          # RGBA is premultiplied: alpha stays
                write_exr(tmp / p.name / f.name, img)
            else:
                os.symlink(f.resolve(), tmp / p.name / f.name)
    os.replace(tmp, out)
    return out


def run_dir(name: str, factor: float, seed: int, extra: Sequence[str] = ()) -> Path:
    """Named by the scene, the exposure factor, the seed and a digest of the fit settings
    (:func:`benchmarks.common.fit_digest`)."""
    return CACHE / "runs" / "exposure" / f"{name}_x{factor:g}_s{seed}_{fit_digest([f'seed={seed}', *extra])}"


def table(names: list[str], factors: list[float], seeds: list[int], extra: Sequence[str] = ()) -> list[str]:
    rows = ["| scene | exposure | seed | albedo PSNR | roughness MSE | specular PSNR | fit min | thr | code |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name in names:
        for f in factors:
            for s in seeds:
                r = run_figures(run_dir(name, f, s, extra))
                if r is not None:
                    rows.append(f"| {name} | x{f:g} | {s} | {r['albedo_psnr']:.2f} | {r['roughness_mse']:.4f} | "
                                f"{r['specular_psnr']:.2f} | {r['fit_s'] / 60:.1f}{'*' if r['resumed'] else ''} | "
                                f"{r['threads']} | {r['code']} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["corner", "leaning"])
    ap.add_argument("--factors", nargs="+", type=float, default=[0.125, 1.0, 8.0])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    fit_arguments(ap)
    ap.add_argument("--note", default="", help="a paragraph printed under the machine line; @FILE reads it from FILE")
    args = ap.parse_args()
    bad = [f for f in args.factors if not f > 0]
    if bad:
        ap.error(f"--factors: {bad[0]:g} is not a positive exposure factor")
    threads = fit_threads(args.threads, args.jobs)
    jobs = []
    for name in args.scenes:
        clean = scene(name, args.res, args.views, args.test_views)
        for f in args.factors:
            data = exposed_scene(clean, f)
            jobs += [(data, name, f, s) for s in args.seeds]
    t0 = time.time()

    def one(job) -> None:
        data, name, f, s = job
        fit_and_eval(data, run_dir(name, f, s, args.extra), set_flags([f"seed={s}", *args.extra], threads),
                     args.eval_spp,
                     f"{name} x{f:g} seed {s}", args.extra)

    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(one, jobs))
    write_results("exposure.md", [
        f"# exposure ({stamp()})", "",
        f"Machine: {machine()}. Built-in scenes with every colour image times the factor, {args.res}x{args.res}, "
        f"{args.views} training views; `cpu` preset{' + ' + ' '.join(args.extra) if args.extra else ''}; eval at "
        f"{args.eval_spp} spp, masked, albedo aligned per view and channel (specular PSNR compares radiance as it is, "
        f"so it moves with the exposure). This invocation: {len(jobs)} runs in "
        f"{(time.time() - t0) / 60:.1f} min (cached runs reused); current code {code_version()}.", "",
        *note_lines(args.note), *table(args.scenes, args.factors, args.seeds, args.extra)])


if __name__ == "__main__":
    main()
