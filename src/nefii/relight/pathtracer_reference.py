"""The deliberately simple sibling of :mod:`nefii.relight.pathtracer`: cosine sampling only.

No emitter sampling, no MIS, no Russian roulette: every vertex draws one cosine-weighted
direction (weight ``f_r pi``), and light is found only where a path escapes to the environment.
Unbiased for the same integral with the same bounce limit, and far noisier; it exists for the
tests to hold the MIS path tracer to (both must agree in mean).
"""
from __future__ import annotations

import math

import torch

from ..raycast.base import Geometry, Rays, spawn_rays
from ..render.estimator import view_above_surface
from ..render.frame import Frame, dot
from ..render.samplers import sample_cosine
from .bsdf import f_r
from ..render.envmap import Environment
from .pathtracer import MaterialFn, PathRadiance, PathSettings


@torch.no_grad()
def trace_paths_reference(rays: Rays, geometry: Geometry, material: MaterialFn, env: Environment,
                          generator: torch.Generator | None, settings: PathSettings = PathSettings()) -> PathRadiance:
    o, d = rays.origins, rays.directions
    offset = settings.ray_offset * geometry.scale
    L = torch.zeros_like(o)
    first = geometry.intersect(Rays(o, d))
    idx = first.valid.nonzero().squeeze(-1)
    β = torch.ones(len(idx), 3, device=o.device, dtype=o.dtype)   # path throughput
    x, n, ng, nl, wo = first.position[idx], first.normal[idx], first.geometric_normal[idx], first.lookup_normal[idx], -d[idx]
    for _ in range(settings.max_bounces):
        keep = dot(ng, wo) > 0                                    # one-sided, as the MIS tracer
        idx, β, x, n, ng, nl, wo = (t[keep] for t in (idx, β, x, n, ng, nl, wo))
        if len(idx) == 0:
            break
        frame = Frame.from_normal(n)
        wi_l = sample_cosine(torch.rand(len(idx), 2, generator=generator, device=o.device, dtype=o.dtype))
        β = β * f_r(material(x, nl), frame.to_local(view_above_surface(n, wo)), wi_l, settings.f0,
                    settings.specular) * math.pi
        wi = frame.to_world(wi_l)
        hit = geometry.intersect(spawn_rays(x, ng, wi, offset))
        esc = ~hit.valid
        L.index_add_(0, idx[esc], β[esc] * env.radiance(wi[esc]))
        h = hit.valid
        idx, β, wo = idx[h], β[h], -wi[h]
        x, n, ng, nl = hit.position[h], hit.normal[h], hit.geometric_normal[h], hit.lookup_normal[h]
    return PathRadiance(radiance=L, hit=first.valid)

