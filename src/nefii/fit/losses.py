"""The two losses NeFII alternates between (paper Eq. 7 and Eq. 8)."""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..geometry.base import Geometry
from .model import NeFIIModel, PathTraced, SurfacePoints, Transport, path_trace
from .pixels import Pixels


def tonemap(x: Tensor, kind: str) -> Tensor:
    """``none``: linear radiance; ``log1p``: compresses highlights so a sun glint does not dominate."""
    if kind == "none":
        return x
    if kind == "log1p":
        return torch.log1p(x.clamp_min(0.0))
    raise ValueError(f"unknown tonemap {kind!r}")


def tonemap_slope(x: Tensor, kind: str) -> Tensor:
    """``d tonemap / dx`` at ``x``: first-order weights that carry the tone map into :func:`pair_distance`."""
    if kind == "none":
        return torch.ones_like(x)
    if kind == "log1p":
        return 1.0 / (1.0 + x.clamp_min(0.0))
    raise ValueError(f"unknown tonemap {kind!r}")


LOSS_KINDS = ("l1", "l2", "l2_pair")


def distance(a: Tensor, b: Tensor, kind: str) -> Tensor:
    """Mean per-channel distance: ``l1`` (the paper's) or ``l2`` (squared; does not treat sparse
    highlights as outliers the way L1 does, which otherwise biases roughness towards glossy).
    ``l2_pair`` is ``l2`` here: it differs only for Monte Carlo estimates (:func:`pair_distance`)."""
    if kind == "l1":
        return (a - b).abs().mean()
    if kind in ("l2", "l2_pair"):
        return (a - b).square().mean()
    raise ValueError(f"unknown loss {kind!r} ({' | '.join(LOSS_KINDS)})")


def pair_distance(a: Tensor, b: Tensor, target: Tensor, tone: str) -> Tensor:
    """``mean(w^2 (a - t)(b - t))`` for two independent estimates ``a``, ``b`` of the same pixels.

    Its expectation is ``w^2 (E[a] - t)^2``: the squared error of the estimate's *mean*. The square of
    one noisy estimate instead adds its variance, and descending on that variance dims whatever
    light is noisy to estimate: a sun found by the light initialisation fades within a few hundred
    steps at N = 8 (it holds at N = 48). ``w`` is the tone map's slope at the target (detached),
    the first-order version of comparing tone-mapped colours, which applied to noisy estimates
    would be biased again (Jensen).
    """
    w = tonemap_slope(target.detach(), tone)
    return ((a - target) * w * (b - target) * w).mean()


def render_distance(traced: PathTraced, target: Tensor, tone: str, kind: str) -> Tensor:
    """The distance between a path-traced colour and ``target`` under loss ``kind``."""
    if kind != "l2_pair":
        return distance(tonemap(traced.radiance.rgb, tone), tonemap(target, tone), kind)
    if traced.pair is None:
        raise ValueError("loss l2_pair needs num_samples >= 2 (two independent half estimates)")
    return pair_distance(traced.pair[0].rgb, traced.pair[1].rgb, target, tone)


@dataclass(frozen=True)
class LossTerms:
    total: Tensor
    render: Tensor
    """L1 of the path-traced colour (Eq. 7, first term; Eq. 8 for the unobserved step)"""
    cache: Tensor
    """L1 of the cache's own colour L(x, n, wo) (Eq. 7, second term)"""
    background: Tensor
    """L2 of the environment seen by background pixels (Eq. 7, third term)"""
    smooth: Tensor | None = None
    """material smoothness prior (not in the paper; 0 weight turns it off)"""


@dataclass(frozen=True)
class SmoothnessPrior:
    """``albedo |a(x) - a(x + d)|_1 + roughness |r(x) - r(x + d)|_1``, ``d ~ N(0, radius^2)`` per axis of the
    tangent plane at ``x``: smoothness along the surface, never through a thin wall to its other face."""

    albedo: float = 0.0
    roughness: float = 0.0
    radius: float = 0.01
    """in world units"""

    @property
    def active(self) -> bool:
        return self.albedo > 0 or self.roughness > 0


def smoothness(model: NeFIIModel, pts: SurfacePoints, material, prior: SmoothnessPrior,
               roughness_override: float | None, generator: torch.Generator | None) -> Tensor:
    """L1 between the material at ``pts`` and at a neighbour a random step along the tangent plane (of the
    unit shading normal), read along the same lookup normal."""
    x, n = pts.position, pts.normal
    d = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype) * prior.radius
    d = d - (d * n).sum(-1, keepdim=True) * n                                 # in the tangent plane
    other = model.material(x + d, pts.lookup_normal, roughness_override=roughness_override)
    loss = prior.albedo * (material.albedo - other.albedo).abs().mean()
    if roughness_override is None:
        loss = loss + prior.roughness * (material.roughness - other.roughness).abs().mean()
    return loss


def observed_loss(model: NeFIIModel, geometry: Geometry, batch: Pixels, num_samples: int,
                  generator: torch.Generator | None, transport: Transport, roughness_override: float | None,
                  beta1: float = 1.0, beta2: float = 1.0, tone: str = "none",
                  prior: SmoothnessPrior = SmoothnessPrior(), kind: str = "l1") -> tuple[LossTerms, PathTraced]:
    """Eq. 7: ``|c_pt - c|_1 + beta1 |L(x,n,wo) - c|_1 + beta2 |E(d_bg) - c_bg|_2^2`` (+ the optional prior)."""
    pts = batch.points
    traced = path_trace(model, geometry, pts, num_samples, generator, transport, roughness_override)
    gt = tonemap(batch.rgb, tone)
    l_render = render_distance(traced, batch.rgb, tone, kind)
    l_cache = distance(tonemap(model.cache(pts.position, pts.normal, pts.wo), tone), gt, kind)
    if len(batch.bg_dirs):
        l_bg = (tonemap(model.env.radiance(batch.bg_dirs), tone) - tonemap(batch.bg_rgb, tone)).square().mean()
    else:
        l_bg = l_render.new_zeros(())
    total = l_render + beta1 * l_cache + beta2 * l_bg
    l_smooth = None
    if prior.active:
        l_smooth = smoothness(model, pts, traced.material, prior, roughness_override, generator)
        total = total + l_smooth
    return LossTerms(total, l_render, l_cache, l_bg, l_smooth), traced


def unobserved_loss(model: NeFIIModel, geometry: Geometry, pts: SurfacePoints, num_samples: int,
                    generator: torch.Generator | None, transport: Transport, roughness_override: float | None,
                    tone: str = "none", kind: str = "l1") -> LossTerms:
    """Eq. 8: L1 between path tracing at secondary hits and the cache there; neither side detached."""
    traced = path_trace(model, geometry, pts, num_samples, generator, transport, roughness_override)
    cached = model.cache(pts.position, pts.normal, pts.wo)
    l = render_distance(traced, cached, tone, kind)
    zero = l.new_zeros(())
    return LossTerms(l, l, zero, zero)


class SecondaryHitBuffer:
    """The secondary hits of recent observed steps, from which Eq. 8 draws uniformly.

    A ring buffer of detached points on the buffer's device; ``capacity`` bounds memory.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._items: SurfacePoints | None = None
        self._next = 0
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def add(self, pts: SurfacePoints) -> None:
        n = min(len(pts), self.capacity)
        if n == 0:
            return
        pts = pts[slice(len(pts) - n, None)].map(Tensor.detach)
        if self._items is None:
            self._items = pts.map(lambda t: t.new_zeros(self.capacity, 3))
        idx = (torch.arange(n, device=pts.position.device) + self._next) % self.capacity
        for f in fields(SurfacePoints):
            getattr(self._items, f.name)[idx] = getattr(pts, f.name)
        self._next = int((self._next + n) % self.capacity)
        self._size = min(self._size + n, self.capacity)

    def sample(self, n: int, generator: torch.Generator | None) -> SurfacePoints:
        assert self._items is not None and self._size > 0, "sample() from an empty buffer"
        idx = torch.randint(self._size, (n,), generator=generator, device=self._items.position.device)
        return self._items[idx]

    def state_dict(self) -> dict | None:
        if self._items is None:
            return None
        return {"next": self._next, "size": self._size, "items": {f.name: getattr(self._items, f.name)
                                                                   for f in fields(SurfacePoints)}}

    def load_state_dict(self, state: dict | None, device: torch.device) -> None:
        if state is None:
            self._items, self._next, self._size = None, 0, 0
            return
        items = {k: v.to(device) for k, v in state["items"].items()}
        items.setdefault("lookup_normal", items["normal"])       # checkpoints from before lookup normals
        self._items = SurfacePoints(**items)
        self._next, self._size = int(state["next"]), int(state["size"])
