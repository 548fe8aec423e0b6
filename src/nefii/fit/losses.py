"""The two losses NeFII alternates between (paper Eq. 7 and Eq. 8), as pure functions of what the
estimator returned, and the ring buffer of secondary hits that Eq. 8 draws from."""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from jaxtyping import Bool, Float

from .path_trace import PathTraced, SurfacePoints


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


def render_distance(traced: PathTraced, target: Tensor, tone: str, kind: str, gain: Tensor | None = None) -> Tensor:
    """The distance between a path-traced colour (times the views' ``gain``, if any) and ``target`` under loss
    ``kind``."""
    g = 1.0 if gain is None else gain
    if kind != "l2_pair":
        return distance(tonemap(g * traced.radiance.rgb, tone), tonemap(target, tone), kind)
    if traced.pair is None:
        raise ValueError("loss l2_pair needs num_samples >= 2 (two independent half estimates)")
    return pair_distance(g * traced.pair[0].rgb, g * traced.pair[1].rgb, target, tone)


@dataclass(frozen=True)
class LossTerms:
    total: Tensor
    render: Tensor
    """distance of the path-traced colour (Eq. 7, first term; Eq. 8 for the unobserved step)"""
    cache: Tensor
    """distance of the cache's own colour L(x, n, wo) (Eq. 7, second term)"""
    background: Tensor
    """L2 of the environment seen by background pixels (Eq. 7, third term)"""
    smooth: Tensor | None = None
    """albedo smoothness prior (not in the paper; None when off)"""
    light: Tensor | None = None
    """the prior on the light where the object barely sees it (:mod:`nefii.fit.light_prior`; None when off)"""
    exposure: Tensor | None = None
    """the per-view gains' prior (:mod:`nefii.fit.exposure`; None with one shared exposure)"""


@dataclass(frozen=True)
class Gains:
    """The view gains of one batch (:mod:`nefii.fit.exposure`) and their prior's value."""

    pixels: Float[Tensor, "B 3"]
    background: Float[Tensor, "G 3"]
    prior: Tensor


@dataclass(frozen=True)
class SmoothnessPrior:
    """``weight |a(x) - a(x + d)|_1``, ``d ~ N(0, radius^2)`` per axis of the tangent plane at ``x``: albedo
    smoothness along the surface, never through a thin wall to its other face."""

    weight: float = 0.0
    radius: float = 0.01
    """in world units"""

    @property
    def active(self) -> bool:
        return self.weight > 0

    def neighbours(self, position: Float[Tensor, "B 3"], normal: Float[Tensor, "B 3"],
                   generator: torch.Generator | None) -> Float[Tensor, "B 3"]:
        """A random step from each point along the tangent plane of its unit shading normal."""
        d = torch.randn(position.shape, generator=generator, device=position.device, dtype=position.dtype) \
            * self.radius
        d = d - (d * normal).sum(-1, keepdim=True) * normal                  # in the tangent plane
        return position + d


def smoothness(albedo: Float[Tensor, "B 3"], neighbour_albedo: Float[Tensor, "B 3"], weight: float) -> Tensor:
    """The prior's value from the albedo at the points and at their neighbours."""
    return weight * (albedo - neighbour_albedo).abs().mean()


def observed_loss(traced: PathTraced, cache_rgb: Float[Tensor, "B 3"], target: Float[Tensor, "B 3"],
                  env_bg: Float[Tensor, "G 3"], target_bg: Float[Tensor, "G 3"], tone: str, kind: str,
                  beta1: float = 1.0, beta2: float = 1.0, smooth: Tensor | None = None,
                  light: Tensor | None = None, gains: Gains | None = None,
                  cache_rows: Bool[Tensor, "B"] | None = None,
                  bg_weight: Float[Tensor, "G"] | None = None) -> LossTerms:
    """Eq. 7: ``d(g c_pt, c) + beta1 d(g L(x,n,wo), c) + beta2 |g E(d_bg) - c_bg|_2^2`` (+ the priors' values),
    ``g`` each pixel's view gain (1 without ``gains``).

    ``cache_rgb`` is the cache's own colour at the pixels' points, ``env_bg`` the environment along the
    background pixels' directions (``G`` may be 0). ``cache_rows``: the pixels the cache's term reads (None: all);
    a pixel whose colour mixes object and sky is no radiance of one surface point. ``bg_weight``: each background
    pixel's weight in the third term (None: 1)."""
    g, g_bg = (1.0, 1.0) if gains is None else (gains.pixels, gains.background)
    l_render = render_distance(traced, target, tone, kind, None if gains is None else gains.pixels)
    if cache_rows is not None:
        cache_rgb, target = cache_rgb[cache_rows], target[cache_rows]
        g = g if gains is None else g[cache_rows]
    l_cache = (distance(tonemap(g * cache_rgb, tone), tonemap(target, tone), kind) if len(cache_rgb)
               else l_render.new_zeros(()))
    if len(env_bg):
        err = (tonemap(g_bg * env_bg, tone) - tonemap(target_bg, tone)).square()
        l_bg = err.mean() if bg_weight is None else (err.mean(-1) * bg_weight).mean()
    else:
        l_bg = l_render.new_zeros(())
    total = l_render + beta1 * l_cache + beta2 * l_bg
    exposure = None if gains is None else gains.prior
    for prior in (smooth, light, exposure):
        if prior is not None:
            total = total + prior
    return LossTerms(total, l_render, l_cache, l_bg, smooth, light, exposure)


def unobserved_loss(traced: PathTraced, cache_rgb: Float[Tensor, "B 3"], tone: str, kind: str) -> LossTerms:
    """Eq. 8: the distance between path tracing at secondary hits and the cache there; neither side detached
    here (what of the material the path-traced side reaches is the caller's choice: ``unobserved_material``)."""
    l = render_distance(traced, cache_rgb, tone, kind)
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
        if self._items is None or self._size == 0:
            raise RuntimeError("SecondaryHitBuffer.sample() before any secondary hit was added (check len() first)")
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
