"""The built-in scenes photographed as a phone would, fitted, and scored against their clean ground truth.

    python -m benchmarks.photo [--scenes bowl cup ...] [--configs mesh mesh_shared geometry] [--jobs 2]

Each scene (128 x 128, 64 views, synthesised once, and again at 256 x 256 for the photos) is turned into a
capture by ``nefii.synth.photo`` (what ``nefii synth SCENE --photo`` writes: 256 x 256 8-bit JPEG, clipped
highlights, per-view exposure within +-1 EV and white-balance drift, lens distortion, noise, no masks, a
nerfstudio ``transforms.json``), then

- ``mesh``: ``nefii fit PHOTO --mesh MESH --set exposure=per_view`` on the scene's true mesh (the photo's
  cameras are the clean scene's, so the mesh is in their world): what the photometric problems cost alone;
- ``mesh_shared``: the same with one exposure for every view (what the per-view gains are worth);
- ``geometry``: ``nefii fit PHOTO --set exposure=per_view`` with no mesh, the one command a user types: the fit
  reconstructs the surface first (``nefii geometry``'s stage into ``RUN/geometry``, no masks: the background
  model; at the stage's own image size, a gain per view) and fits on it; the whole path from a capture to
  materials (~30 min a scene, two at a time on 2 cores);

each scored by ``nefii eval RUN --data CLEAN`` on the clean test views (albedo aligned per view and
channel, so the capture's unknown overall exposure does not count). The clean-input reference is the
quality benchmark's ``full`` run on the same scene (``benchmarks.quality``; true mesh, masked) for the
mesh rows and the geometry benchmark's masked reconstruction fit where it exists. Writes
``benchmarks/results/photo.md`` with every finished run of the seed, this invocation's or earlier.
Target (issue 30): albedo PSNR within 1.5 dB and roughness MSE within 1.5x of the clean-input fit on the
same geometry path, every scene.
"""
from __future__ import annotations

import argparse
import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .common import (CACHE, code_version, fit_and_eval, fit_digest, fit_threads, machine, scene, set_flags, stamp,
                     write_results)
from .geometry import geometry_folder, stage_digest
from .quality import SCENES, run_dir

CONFIGS = {
    "mesh": ["exposure=per_view"],
    "mesh_shared": ["exposure=shared"],
    "geometry": ["exposure=per_view"],
}
KEYS = ("albedo_psnr", "roughness_mse", "specular_psnr", "rgb_psnr")


RES = 128
"""the clean scene's resolution, and the fits' (``max_image_side``)"""
PHOTO_SCALE = 2
"""the photos are taken at this multiple of ``RES`` (as ``nefii synth --photo``) and averaged down by the fit"""


def photo_scene(name: str) -> tuple[Path, Path]:
    """(clean scene, its photographed capture), each made once into the cache."""
    from nefii.synth.photo import make_photos  # noqa: PLC0415

    clean = scene(name, res=RES)
    photo = CACHE / f"{clean.name}_photo{PHOTO_SCALE}x"
    if not (photo / "transforms.json").exists():
        make_photos(clean, photo, render=scene(name, res=PHOTO_SCALE * RES))
    return clean, photo


def photo_sets(config: str, seed: int) -> list[str]:
    """The fit settings of a ``config`` run at ``seed``."""
    return [*CONFIGS[config], f"seed={seed}", f"max_image_side={RES}"]


def photo_run(name: str, config: str, seed: int) -> Path:
    """The cached run, named by a digest of its fit settings and, for a ``geometry`` run, of its stage's (a run made
    at other defaults, another preset's steps say, is not reused)."""
    stage = f"_{stage_digest('cpu', [])}" if config == "geometry" else ""
    return CACHE / "runs" / f"photo_{name}_{config}_s{seed}{stage}_{fit_digest(photo_sets(config, seed))}"


def run_one(name: str, config: str, seed: int, threads: int) -> None:
    clean, photo = photo_scene(name)
    run = photo_run(name, config, seed)
    if (run / "eval" / "metrics.json").exists():
        return
    where = [] if config == "geometry" else ["--mesh", str(clean / "mesh.ply")]
    fit_and_eval(photo, run, [*where, *set_flags(photo_sets(config, seed), threads)],
                 64, f"{name}/{config}", eval_args=["--data", str(clean)])


def metrics(run: Path) -> dict | None:
    path = run / "eval" / "metrics.json"
    return json.loads(path.read_text())["masked"] if path.exists() else None


def reference(name: str, config: str) -> dict | None:
    """The clean-input fit on the same geometry path."""
    if config == "geometry":  # benchmarks.geometry's masked reconstruction and its fit
        data = scene(name)
        return metrics(geometry_folder(data.name, "on", "cpu", []) / f"fit_{data.name}")
    return metrics(run_dir(name, "full"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--configs", nargs="+", default=["mesh", "mesh_shared"], choices=list(CONFIGS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2, help="fits at once, one thread each (default 2)")
    ap.add_argument("--threads", type=int, default=None, help="threads per fit (default: 1 with --jobs > 1, else all)")
    args = ap.parse_args()
    jobs = [(s, c) for s in args.scenes for c in args.configs]
    threads = fit_threads(args.threads, args.jobs)
    with ThreadPoolExecutor(args.jobs) as pool:
        for f in [pool.submit(run_one, s, c, args.seed, threads) for s, c in jobs]:
            f.result()

    lines = [f"# photo ({stamp()}, code {code_version()})", "",
             f"Machine: {machine()}. Fits {args.jobs} at a time, {'one thread each' if threads == 1 else 'all cores'}; "
             f"`cpu` preset; photos at {PHOTO_SCALE * RES} px averaged down to {RES} px by the fit (`max_image_side`); "
             "eval at 64 spp on the clean test views. Generated by `python -m benchmarks.photo`.", "",
             "Masked figures: albedo PSNR dB / roughness MSE / specular PSNR dB / RGB PSNR dB. 'clean' is the same "
             "scene's clean-input fit on the same geometry path (quality.md's `full` run for the mesh rows). "
             "Target: albedo within 1.5 dB and roughness MSE within 1.5x of clean.", "",
             "| scene | config | photo | clean | albedo vs clean | roughness vs clean | target |",
             "|---|---|---|---|---|---|---|"]
    fmt = lambda m: " / ".join(f"{m[k]:.4f}" if k == "roughness_mse" else f"{m[k]:.2f}" for k in KEYS)  # noqa: E731
    for s, c in [(s, c) for s in SCENES for c in CONFIGS]:  # every finished run, this invocation's or earlier
        m, ref = metrics(photo_run(s, c, args.seed)), reference(s, c)
        if m is None:
            continue
        if ref is None:
            lines.append(f"| {s} | {c} | {fmt(m)} | - | - | - | - |")
            continue
        d_alb, r_rough = m["albedo_psnr"] - ref["albedo_psnr"], m["roughness_mse"] / ref["roughness_mse"]
        met = "met" if d_alb >= -1.5 and r_rough <= 1.5 else "NOT met"
        lines.append(f"| {s} | {c} | {fmt(m)} | {fmt(ref)} | {d_alb:+.2f} dB | {r_rough:.2f}x | {met} |")
    write_results("photo.md", lines)


if __name__ == "__main__":
    main()
