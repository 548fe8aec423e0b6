"""Eq. 2-4 for a batch of surface points: N estimator samples by MIS, one secondary ray per direction,
``V E(w)`` where it escapes and the cache ``L(x', n', -w)`` where it hits (paper Sec. 3.2).

The material at the points is an input (the caller decodes it once, :func:`nefii.fit.model.decode_material`);
the secondary hits come back with the estimate: they are the unobserved rays of Eq. 8.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Callable

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from ..raycast.base import Geometry, Rays, SurfaceHit, spawn_rays
from ..render.brdf import Material
from ..render.estimator import (DirectionSamples, RadianceEstimate, combine, combine_pair, mean_of_pair,
                                sample_mis_directions)
from .model import NeFIIModel


@dataclass(frozen=True)
class SurfacePoints:
    """Points on the frozen surface seen along ``wo`` (first hits, or secondary hits reused)."""

    position: Float[Tensor, "B 3"]
    normal: Float[Tensor, "B 3"]
    """unit shading normal"""
    geometric_normal: Float[Tensor, "B 3"]
    wo: Float[Tensor, "B 3"]
    """unit direction towards the viewer"""
    lookup_normal: Float[Tensor, "B 3"]
    """unit normal along which the material lookup is offset (:attr:`SurfaceHit.lookup_normal`)"""

    @staticmethod
    def from_hit(hit: SurfaceHit, select: Tensor, wo: Float[Tensor, "B 3"]) -> "SurfacePoints":
        """The hits ``hit[select]`` (an index or mask over the rays) seen along ``wo`` (one per selected hit)."""
        return SurfacePoints(hit.position[select], hit.normal[select], hit.geometric_normal[select], wo,
                             hit.lookup_normal[select])

    def map(self, fn: Callable[[Tensor], Tensor]) -> "SurfacePoints":
        """``fn`` applied to every field (indexing, detaching, moving, ...)."""
        return SurfacePoints(*(fn(getattr(self, f.name)) for f in fields(SurfacePoints)))

    def __getitem__(self, idx: Tensor | slice) -> "SurfacePoints":
        return self.map(lambda t: t[idx])

    @staticmethod
    def cat(items: list["SurfacePoints"]) -> "SurfacePoints":
        return SurfacePoints(*(torch.cat([getattr(p, f.name) for p in items]) for f in fields(SurfacePoints)))

    def __len__(self) -> int:
        return self.position.shape[0]


@dataclass(frozen=True)
class Transport:
    """Which light paths the estimator follows (the ablation switches of Sec. 4.3), and how rays leave."""

    indirect: bool = True
    """secondary rays that hit the object see the radiance cache; off: they see black"""
    visibility: bool = True
    """off: every direction sees the environment, as if nothing occluded it (PhySG-style)"""
    ray_offset: float = 1e-4
    """secondary rays start this far off the surface, a fraction of the geometry's bounding-box diagonal"""


@dataclass(frozen=True)
class PathTraced:
    radiance: RadianceEstimate
    """the estimate from all N estimator samples"""
    pair: tuple[RadianceEstimate, RadianceEstimate] | None
    """two independent estimates from either half of the samples (None when N < 2)"""
    secondary: SurfacePoints
    """secondary hits ``(x', n', -w)``: where the cache was queried"""


def two_point_pair(traced: PathTraced, half: int) -> PathTraced:
    """A batch traced at two points of each of ``half`` pixels (the first ``half`` points, then the second) as
    one estimate per pixel: the two points' mean, and the two as its independent pair."""
    first, second = (RadianceEstimate(traced.radiance.diffuse[s], traced.radiance.specular[s])
                     for s in (slice(None, half), slice(half, None)))
    return PathTraced(mean_of_pair((first, second), 2), (first, second), traced.secondary)


def environment_where(traced: PathTraced, sky: Bool[Tensor, "B"], radiance: Float[Tensor, "B 3"]) -> PathTraced:
    """``traced`` with its rows ``sky`` replaced by the environment's ``radiance`` along their rays (as diffuse, with
    no specular part): the parts of a pixel's footprint that see past the object. Those rows' estimates, and their
    gradients, are dropped; ``radiance``'s other rows are not read. Secondary hits are kept."""
    at = sky.unsqueeze(-1)

    def swap(e: RadianceEstimate) -> RadianceEstimate:
        return RadianceEstimate(torch.where(at, radiance.to(e.diffuse), e.diffuse),
                                torch.where(at, torch.zeros_like(e.specular), e.specular))

    pair = None if traced.pair is None else (swap(traced.pair[0]), swap(traced.pair[1]))
    return PathTraced(swap(traced.radiance), pair, traced.secondary)


def _estimate(samples: DirectionSamples, material: Material, n: Tensor, L_i: Tensor
              ) -> tuple[RadianceEstimate, tuple[RadianceEstimate, RadianceEstimate] | None]:
    N = samples.num_estimator_samples
    if N < 2:
        return combine(samples, material, n, L_i), None
    pair = combine_pair(samples, material, n, L_i)
    return mean_of_pair(pair, N), pair


def sample_directions(pts: SurfacePoints, material: Material, sampler, num_samples: int,
                      generator: torch.Generator | None) -> DirectionSamples:
    """The estimator's MIS directions at ``pts`` with the ``material`` there (no gradient through them)."""
    return sample_mis_directions(pts.normal, pts.wo, material.roughness.detach(), sampler, num_samples, generator)


@dataclass(frozen=True)
class LiveSamples:
    """The directions that carry weight (only they are traced and lit), with their secondary rays' hits."""

    point: Int[Tensor, " L"]
    sample: Int[Tensor, " L"]
    direction: Float[Tensor, "L 3"]
    hit: SurfaceHit | None
    """None without visibility (every direction then sees the environment)"""

    @property
    def escapes(self) -> Bool[Tensor, " L"]:
        if self.hit is None:
            return torch.ones(len(self.direction), dtype=torch.bool, device=self.direction.device)
        return ~self.hit.valid


def trace_live_samples(pts: SurfacePoints, samples: DirectionSamples, geometry: Geometry,
                       transport: Transport) -> LiveSamples:
    """The weighted directions of ``samples`` and, with visibility, their secondary rays cast."""
    b_idx, s_idx = (samples.weight > 0).nonzero(as_tuple=True)
    w_live = samples.wi[b_idx, s_idx]
    if not transport.visibility:
        return LiveSamples(b_idx, s_idx, w_live, None)
    rays = spawn_rays(pts.position[b_idx], pts.geometric_normal[b_idx], w_live, transport.ray_offset * geometry.scale)
    return LiveSamples(b_idx, s_idx, w_live, geometry.intersect(Rays(rays.origins, rays.directions)))


def path_trace(model: NeFIIModel, geometry: Geometry, pts: SurfacePoints, material: Material, num_samples: int,
               generator: torch.Generator | None, transport: Transport = Transport(),
               shading_normal: Float[Tensor, "B 3"] | None = None,
               environment: Callable[[Tensor], Tensor] | None = None) -> PathTraced:
    """Eq. 2-4 at ``pts`` with the ``material`` there: the path-traced colour and the secondary hits.
    ``shading_normal`` (default ``pts.normal``) is the normal the estimate's terms are evaluated with while
    the directions are drawn, weighted and traced from ``pts.normal``: a geometry refinement passes the SDF's
    differentiable normal here, and the samples' densities and visibility stay constants of its gradient.
    ``environment`` (default ``model.env.radiance``) gives the radiance of the directions that escape."""
    n = pts.normal if shading_normal is None else shading_normal
    radiance = model.env.radiance if environment is None else environment
    samples = sample_directions(pts, material, model.env.light_sampler(), num_samples, generator)
    wi = samples.wi                                                            # (B, S, 3)
    live = trace_live_samples(pts, samples, geometry, transport)
    b_idx, s_idx, w_live, hit = live.point, live.sample, live.direction, live.hit
    if hit is None:
        L_i = wi.new_zeros(wi.shape).index_put((b_idx, s_idx), radiance(w_live))
        no_hits = SurfacePoints(*(wi.new_zeros(0, 3) for _ in fields(SurfacePoints)))
        return PathTraced(*_estimate(samples, material, n, L_i), no_hits)

    # ---- secondary rays
    secondary = SurfacePoints.from_hit(hit, hit.valid, -w_live[hit.valid])
    # ---- incoming light: V E(w) + (1 - V) L(x', n', -w)
    miss = ~hit.valid
    if environment is None and samples.light_lobes is not None:     # the light pdf's lobe values, not again
        L_miss = model.env.radiance(w_live[miss], samples.light_lobes[b_idx[miss], s_idx[miss]])
    else:
        L_miss = radiance(w_live[miss])
    L_i = wi.new_zeros(wi.shape).index_put((b_idx[miss], s_idx[miss]), L_miss)
    if transport.indirect and len(secondary):
        L_hit = model.cache(secondary.position, secondary.normal, secondary.wo)
        L_i = L_i.index_put((b_idx[hit.valid], s_idx[hit.valid]), L_hit)
    return PathTraced(*_estimate(samples, material, n, L_i), secondary)
