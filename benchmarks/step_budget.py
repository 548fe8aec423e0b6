"""Where a training step's time goes, against the ray caster: the part of issue 28's gap that is arithmetic.

``fit_speed`` measures the step's throughput; this module says what a step must do at the least. In the
steps it times it records, per step, the wall time spent inside Embree (``intersect`` and ``occluded``) and
the rows the radiance cache and the material field are evaluated at; then it times, alone, one forward and
backward pass of each network at those rows (their encodings and MLPs as the fit configures them, on random
points in the scene's box). Embree's time plus the two networks' passes is a floor for the step as it is
designed: what a step would cost with no PyTorch overhead at all, no shading arithmetic and no optimiser.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor, nn

from nefii.render.frame import normalize


@dataclass(frozen=True)
class StepBudget:
    """Per-step averages over the timed steps (``ms`` wall milliseconds, ``rows`` network evaluations)."""

    steps: int
    step_ms: float
    embree_ms: float
    embree_rays: float
    cache_rows: float
    material_rows: float
    cache_pass_ms: float
    """one forward and backward pass of the radiance cache at ``cache_rows`` rows, alone"""
    material_pass_ms: float
    """the same for the material field at ``material_rows`` rows"""

    @property
    def floor_ms(self) -> float:
        return self.embree_ms + self.cache_pass_ms + self.material_pass_ms


def _timed(fn: Callable[..., Any], clock: list[float], count: list[float], rays_of: Callable[..., int]):
    def wrapper(*args, **kwargs):
        t = time.perf_counter()
        out = fn(*args, **kwargs)
        clock[0] += time.perf_counter() - t
        count[0] += rays_of(*args, **kwargs)
        return out
    return wrapper


def _rows_hook(count: list[float]):
    def hook(_module: nn.Module, args: tuple) -> None:
        count[0] += args[0].shape[:-1].numel()
    return hook


def _pass_ms(net: nn.Module, make_inputs: Callable[[], tuple[Tensor, ...]], repeats: int) -> float:
    """Best wall time of ``repeats`` forward + backward passes of ``net`` (after two to warm up)."""
    inputs = make_inputs()
    best = float("inf")
    for i in range(repeats + 2):
        net.zero_grad(set_to_none=True)
        t = time.perf_counter()
        out = net(*inputs)
        value = out if isinstance(out, Tensor) else torch.cat([out.albedo, out.roughness[..., None]], -1)
        value.sum().backward()
        if i >= 2:
            best = min(best, time.perf_counter() - t)
    net.zero_grad(set_to_none=True)
    return 1000 * best


def measure(trainer: Any, geometry: Any, steps: int, repeats: int = 5) -> StepBudget:
    """Run ``steps`` training steps of ``trainer`` with Embree's calls timed and the networks' rows counted,
    then time each network's pass alone at those rows. ``geometry`` is the trainer's mesh geometry."""
    clock, rays = [0.0], [0.0]
    cache_rows, material_rows = [0.0], [0.0]
    saved = {name: getattr(geometry, name) for name in ("intersect", "occluded")}
    for name, fn in saved.items():
        setattr(geometry, name, _timed(fn, clock, rays, lambda r, *a, **k: r.origins.shape[:-1].numel()))
    model = trainer.model
    hooks = [model.cache.register_forward_pre_hook(_rows_hook(cache_rows)),
             model.material.register_forward_pre_hook(_rows_hook(material_rows))]
    try:
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        step_s = (time.perf_counter() - t0) / steps
    finally:
        for h in hooks:
            h.remove()
        for name in saved:
            delattr(geometry, name)      # the class's methods again
    lo, size = model.cache.box_lo, model.cache.box_size
    g = torch.Generator(device=lo.device).manual_seed(0)

    def points(n: int) -> Tensor:
        return lo + size * torch.rand(n, 3, generator=g, device=lo.device)

    def dirs(n: int) -> Tensor:
        return normalize(torch.randn(n, 3, generator=g, device=lo.device))

    nc, nm = round(cache_rows[0] / steps), round(material_rows[0] / steps)
    cache_ms = _pass_ms(model.cache, lambda: (points(nc), dirs(nc), dirs(nc)), repeats)
    material_ms = _pass_ms(model.material, lambda: (points(nm), dirs(nm)), repeats)
    return StepBudget(steps, 1000 * step_s, 1000 * clock[0] / steps, rays[0] / steps, nc, nm, cache_ms, material_ms)


def rows(b: StepBudget, samples_per_step: float, closest_rate: float, target_share: float = 0.15
         ) -> list[tuple[str, str]]:
    """The figures of :class:`StepBudget` as ``fit_speed``'s table rows, beside the step time that
    ``target_share`` of Embree's closest-hit rate would allow for ``samples_per_step`` direction samples."""
    budget_ms = 1000 * samples_per_step / (target_share * closest_rate)
    floor_share = samples_per_step / (b.floor_ms / 1000) / closest_rate
    return [
        ("step time with Embree's calls timed (separate run of steps)", f"{b.step_ms:.1f} ms ({b.steps} steps)"),
        ("of it inside Embree (closest and any hit)", f"{b.embree_ms:.1f} ms for {b.embree_rays:.0f} rays"),
        ("radiance cache rows a step; one forward + backward pass of the cache at them, alone",
         f"{b.cache_rows:.0f}; {b.cache_pass_ms:.1f} ms"),
        ("material field rows a step; one forward + backward pass at them, alone",
         f"{b.material_rows:.0f}; {b.material_pass_ms:.1f} ms"),
        ("floor: Embree + the two networks' passes", f"{b.floor_ms:.1f} ms, {b.floor_ms / b.step_ms:.0%} of the step"),
        (f"step time at {target_share:.0%} of Embree's closest-hit rate", f"{budget_ms:.1f} ms"),
        ("training samples/s over Embree closest-hit rate at the floor", f"{floor_share:.3f}"),
    ]
