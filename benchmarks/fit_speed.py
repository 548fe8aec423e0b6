"""Speed and memory of the ``cpu`` preset's training step, beside the raw Embree ray-cast rate.

    python -m benchmarks.fit_speed [--data DIR] [--steps 200] [--preset cpu] [--device auto|cpu|cuda]

The fit is set up as ``nefii fit`` sets it up (``nefii.fit.session.prepare_fit``: first hits, model,
light initialisation). Prints the figures and writes ``benchmarks/results/fit_speed.md`` (``fit_speed_cuda.md`` when the
step runs on a GPU; Embree's ray casts stay on the CPU either way). Without ``--data`` it uses
the smallest built-in scene at 128x128 with 64 training views (synthesised once, cached). On the CPU the
table ends with :mod:`benchmarks.step_budget`'s rows: the step's time inside Embree and its networks' passes.
"""
from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import torch

from nefii.cli.common import pick_device, set_threads
from nefii.fit.config import resolve_config
from nefii.fit.session import prepare_fit
from nefii.raycast import MeshGeometry, Rays
from nefii.render.frame import normalize
from nefii.synth import smallest_scene

from . import step_budget
from .common import machine, scene, stamp, write_results


def embree_rate(geometry: MeshGeometry, n: int = 1_000_000, repeats: int = 3) -> tuple[float, float]:
    """Closest-hit and any-hit rays per second for random rays through the scene's bounding sphere."""
    g = torch.Generator().manual_seed(0)
    lo, hi = (torch.from_numpy(b.copy()) for b in geometry.bounds)
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo).norm()
    o = c + normalize(torch.randn(n, 3, generator=g)) * r * 1.5
    d = normalize(c + torch.randn(n, 3, generator=g) * r * 0.5 - o)
    rays = Rays(o, d)
    best_i, best_o = 0.0, 0.0
    for _ in range(repeats):
        t = time.perf_counter()
        geometry.intersect(rays)
        best_i = max(best_i, n / (time.perf_counter() - t))
        t = time.perf_counter()
        geometry.occluded(rays)
        best_o = max(best_o, n / (time.perf_counter() - t))
    return best_i, best_o


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    args = ap.parse_args()
    device = pick_device(args.device)
    data = args.data or scene(smallest_scene())
    cfg = resolve_config(args.preset, [])
    threads = set_threads(cfg.threads)
    t0 = time.perf_counter()
    session = prepare_fit(cfg, data, device=device)
    t_setup = time.perf_counter() - t0
    cfg, sc, geometry, pixels, trainer = session.config, session.scene, session.geometry, session.pixels, session.trainer
    for _ in range(10):  # warm up (allocator, first unobserved step)
        trainer.train_step()
    rays = 0
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    sync()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        rec = trainer.train_step()
        rays += 3 * cfg.num_samples * (cfg.batch_pixels if rec.kind == "observed" else cfg.unobserved_points)
    sync()
    dt = time.perf_counter() - t0
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    closest, anyhit = embree_rate(geometry)
    steps_s = args.steps / dt
    rays_s = rays / dt
    budget = step_budget.measure(trainer, geometry, max(args.steps // 2, 20)) if device.type == "cpu" else None
    rows = [
        ("scene", f"{data.name}: {len(sc)} views {sc.width}x{sc.height}, {len(pixels.points)} object pixels, "
                  f"{len(geometry.faces)} triangles"),
        ("preset", f"{args.preset}: {cfg.batch_pixels} px/step, N={cfg.num_samples} (x3 directions)"),
        ("device of the training step", str(device)),
        ("CPU threads (Embree, and the step on the CPU)", str(threads)),
        ("fit setup (first hits of all training pixels, model, light initialisation)", f"{t_setup:.2f} s"),
        ("steps/s", f"{steps_s:.2f}"),
        ("time per step", f"{1000 / steps_s:.1f} ms"),
        ("direction samples/s (secondary rays + their shading)", f"{rays_s / 1e6:.3f} M"),
        ("Embree closest-hit rays/s (same machine, same mesh)", f"{closest / 1e6:.2f} M"),
        ("Embree any-hit rays/s", f"{anyhit / 1e6:.2f} M"),
        ("training samples/s over Embree closest-hit rate", f"{rays_s / closest:.3f}"),
        ("steps in 15 min at this rate", f"{steps_s * 900:.0f} (preset runs {cfg.steps})"),
        ("peak resident memory", f"{peak_gib:.2f} GiB"),
    ]
    if budget is not None:
        rows += step_budget.rows(budget, rays / args.steps, closest)
    if device.type == "cuda":
        rows.append(("peak GPU memory allocated", f"{torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB"))
    md = [f"# fit_speed ({stamp()})", "", f"Machine: {machine()}", "", "| figure | value |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in rows]
    write_results("fit_speed_cuda.md" if device.type == "cuda" else "fit_speed.md", md)


if __name__ == "__main__":
    main()
