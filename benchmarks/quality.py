"""Table 1 on the built-in scenes: the full model and the four ablations of Sec. 4.3.

    python -m benchmarks.quality [--scenes bowl cup ...] [--configs full indirect_off ...]
                                 [--res 128] [--views 64] [--jobs 2] [--set key=value ...]

Each (scene, config) is ``nefii fit`` (``cpu`` preset plus the ablation's switch) then
``nefii eval``; runs live in ``benchmarks/.cache/runs``, in a folder per scene, config and digest of the fit
settings they resolve to, and are reused when complete (each records the commit that fitted it). Writes ``benchmarks/results/quality.md`` with the masked Table 1 columns,
wall time, peak memory and code version of every completed run of the default scenes and configs
(so runs done at different times accumulate; those not run yet are listed), machine and versions. ``--jobs 2`` runs two fits at once with one thread each
(two 2-thread processes on 2 cores slowed each other down ~10x before nefii set OpenMP threads to wait passively; not remeasured since).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .common import (CACHE, code_version, fit_and_eval, fit_arguments, fit_digest, fit_threads, machine, note_lines,
                     run_figures, scene,
                     set_flags, stamp, write_results)

CONFIGS = {
    "full": [],
    "light_envmap": ["light.kind=envmap"],
    "unobserved_off": ["unobserved=off"],
    "indirect_off": ["indirect=off"],
    "visibility_off": ["visibility=off"],
}
BASELINES = {
    "physg": ["visibility=off", "indirect=off"],
}
"""the paper's baselines as nefii configurations (benchmarks/peers); not in quality.md's default table"""
COLUMNS = ("roughness_mse", "albedo_psnr", "albedo_ssim", "specular_psnr", "specular_ssim", "rgb_psnr", "rgb_ssim")


SCENES = ("bowl", "leaning", "cup", "corner")


def run_dir(name: str, config: str, extra: Sequence[str] = ()) -> Path:
    """The cached run of ``config`` (plus the ``extra`` overrides) on scene ``name``: named by both and by a digest of
    the fit settings they resolve to (:func:`benchmarks.common.fit_digest`)."""
    switches = {**CONFIGS, **BASELINES}[config]
    return CACHE / "runs" / f"{name}_{config}_{fit_digest([*switches, *extra])}"


def run_one(data: Path, name: str, config: str, extra: list[str], threads: int, eval_spp: int) -> None:
    switches = {**CONFIGS, **BASELINES}[config]
    fit_and_eval(data, run_dir(name, config, extra), set_flags([*switches, *extra], threads), eval_spp,
                 f"{name}/{config}", extra)


def relight_one(data: Path, name: str, spp: int, extra: Sequence[str] = ()) -> None:
    """``nefii relight`` of the scene's full-model run under each of its relighting environments."""
    run = run_dir(name, "full", extra)
    for env in sorted((data / "relight").glob("*.exr")):
        done, record = run / "relight" / "metrics.json", run / "relight" / env.stem / "render.json"
        if (done.exists() and env.stem in json.loads(done.read_text()) and record.exists()
                and json.loads(record.read_text()).get("spp") == spp):
            continue
        subprocess.run([sys.executable, "-m", "nefii.cli.main", "relight", str(run), "--envmap", str(env), "--spp",
                        str(spp), "--quiet"], check=True, capture_output=True)


def relight_rows(name: str, extra: Sequence[str] = ()) -> list[str]:
    path = run_dir(name, "full", extra) / "relight" / "metrics.json"
    if not path.exists():
        return []
    blob = json.loads(path.read_text())
    return [f"| {name} | {env} | {e['psnr']:.2f} | {e['ssim']:.4f} | {'met' if e['psnr'] >= 26 else 'NOT met'} |"
            for env, e in sorted(blob.items()) if isinstance(e, dict) and e.get("psnr") is not None]


def read_row(name: str, config: str, extra: Sequence[str] = ()) -> dict | None:
    """The completed run's figures (:func:`run_figures`), or None."""
    figures = run_figures(run_dir(name, config, extra))
    return None if figures is None else {"scene": name, "config": config, **figures}


def target_lines(rows: list[dict]) -> list[str]:
    """The issue's quality targets against the full model's rows (generated from the figures)."""
    by = {(r["scene"], r["config"]): r for r in rows}
    out = ["Targets (full model): albedo PSNR >= 26 dB, roughness MSE <= 0.02, albedo >= 0.5 dB ahead of "
           "`indirect_off`, peak <= 4 GiB:", ""]
    for name in SCENES:
        full, off = by.get((name, "full")), by.get((name, "indirect_off"))
        if full is None:
            continue
        gain = "n/a" if off is None else f"{full['albedo_psnr'] - off['albedo_psnr']:+.2f} dB"
        ok = lambda c: "met" if c else "NOT met"  # noqa: E731
        out.append(f"- {name}: albedo {full['albedo_psnr']:.2f} dB ({ok(full['albedo_psnr'] >= 26)}), roughness "
                   f"{full['roughness_mse']:.4f} ({ok(full['roughness_mse'] <= 0.02)}), vs indirect_off {gain}"
                   + ("" if off is None else f" ({ok(full['albedo_psnr'] - off['albedo_psnr'] >= 0.5)})")
                   + f", peak {full['peak_gib']:.2f} GiB ({ok(full['peak_gib'] <= 4)})")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS))
    fit_arguments(ap)
    ap.add_argument("--relight-spp", type=int, default=256,
                    help="paths per pixel of the relighting, default `nefii relight`'s own (0: skip it)")
    ap.add_argument("--note", default="", help="a paragraph printed under the machine line of quality.md and "
                    "relight.md (how the rows were made, when that is not this invocation); @FILE reads it from FILE")
    args = ap.parse_args()
    note = note_lines(args.note)
    datas = {s: scene(s, args.res, args.views, args.test_views) for s in args.scenes}
    threads = fit_threads(args.threads, args.jobs)
    jobs = [(datas[s], s, c) for s in args.scenes for c in args.configs]
    t0 = time.time()
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda j: run_one(*j, args.extra, threads, args.eval_spp), jobs))
        if args.relight_spp > 0 and "full" in args.configs:
            list(pool.map(lambda s: relight_one(datas[s], s, args.relight_spp, args.extra), args.scenes))
    order = list(dict.fromkeys([*SCENES, *args.scenes]))
    found = {(s, c): read_row(s, c, args.extra) for s in order for c in CONFIGS}
    rows = [r for r in found.values() if r is not None]
    missing = [f"{s}/{c}" for (s, c), r in found.items() if r is None]
    lines = [f"# quality ({stamp()})", "",
             f"Machine: {machine()}. Scenes {args.res}x{args.res}, {args.views} training views, "
             f"{args.test_views} test views; `cpu` preset{' + ' + ' '.join(args.extra) if args.extra else ''}; "
             f"eval at {args.eval_spp} spp. Fit time is each fit's wall time with its own thread count (`thr`); "
             f"fits run two at a time (1 thread each) take ~1.5x as long as a lone fit on both cores. This "
             f"invocation: {len(jobs)} runs in {(time.time() - t0) / 60:.1f} min (cached runs reused); current code "
             f"{code_version()}.", "", *note,
             "Masked (object pixels) Table 1 columns; LPIPS n/a offline. Albedo aligned per view and channel "
             "by median(gt/pred).", "",
             "| scene | config | " + " | ".join(COLUMNS) + " | rgb PSNR (whole image) | fit min | thr | peak GiB | code |",
             "|---|---|" + "---|" * (len(COLUMNS) + 5)]
    for r in rows:
        vals = [("n/a" if r[k] is None else f"{r[k]:.4f}" if "mse" in k or "ssim" in k else f"{r[k]:.2f}")
                for k in COLUMNS]
        lines.append(f"| {r['scene']} | {r['config']} | " + " | ".join(vals)
                     + f" | {r['whole']['rgb_psnr']:.2f} | {r['fit_s'] / 60:.1f}{'*' if r['resumed'] else ''} | {r['threads']} | {r['peak_gib']:.2f} | {r['code']} |")
    if any(r["resumed"] for r in rows):
        lines += ["", "\\* resumed fit: the time is its last session's rate scaled to all its steps."]
    lines += ["", *target_lines(rows)]
    if missing:
        lines += ["", "Not run yet: " + ", ".join(missing) + "."]
    write_results("quality.md", lines)
    relit = [row for s in order for row in relight_rows(s, args.extra)]
    if relit:
        write_results("relight.md", [
            f"# relight ({stamp()})", "", f"Machine: {machine()}. `nefii relight` of each scene's `full` run of "
            f"quality.md (fitted under its training light) under the scene's relighting environments, test views, "
            f"{args.relight_spp} spp, 8 bounces; object pixels, sRGB clipped, albedo scaled by eval's alignment. "
            f"Target: >= 26 dB masked PSNR.", "", *note, "| scene | environment | PSNR | SSIM | target |", "|---|---|---|---|---|",
            *relit])


if __name__ == "__main__":
    main()
