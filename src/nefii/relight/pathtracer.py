"""Multi-bounce path tracing of the frozen mesh, with the recovered materials, under an environment map.

Estimates the rendering equation with its full recursion (every bounce, not the radiance cache,
which holds the old lighting)::

    L(x, wo) = ∫ f_r(x, wo, wi) L_i(x, wi) (n . wi) dwi,   L_i = E(wi) where the ray escapes,
                                                              L(x', -wi) where it hits x'

Each path vertex does what Mitsuba's ``path`` integrator does (Veach's next-event estimation):

* **emitter sampling**: one direction from the environment's piecewise-constant 2D distribution
  (``nefii.render.envmap``), a shadow ray, weighted by the power heuristic against the BSDF pdf;
* **BSDF sampling**: one direction from the mixture of cosine and GGX visible normals
  (:mod:`nefii.relight.bsdf`); the ray is traced, and where it **escapes** the environment
  counts with the power-heuristic weight against the environment pdf (so the two strategies
  add up to one estimator of the direct light), where it **hits** the path goes on;
* **stopping**: after ``max_bounces`` surface interactions (1 = direct light only), and by
  Russian roulette from ``rr_depth`` bounces on (survive with ``min(max β, 0.95)``, ``β /= q``).

Supports: the simplified Disney BRDF of :mod:`nefii.render.brdf` (Lambert + GGX, ``F0 = 0.04``)
from any material function ``(x, lookup normal) -> Material`` (the fitted model's
``decode_material``); shading normals; the environment as the only light.
Does not: emissive surfaces, transmission, delta lobes (roughness >= 0.089 keeps GGX finite),
two-sided surfaces (a ray reaching the back of a triangle ends there, as Mitsuba's principled
BSDF is one-sided), pixel filtering or cameras (the caller gives the primary rays), gradients.
Batches are flat: ``P`` paths; the caller chunks them for memory.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..raycast.base import Geometry, Rays, spawn_rays
from ..render.brdf import F0_DIELECTRIC, Material, alpha_from_roughness
from ..render.estimator import view_above_surface
from ..render.frame import Frame, dot
from ..render.mis import power_heuristic, power_heuristic_over_pdf
from .bsdf import f_r, pdf_bsdf, sample_bsdf, specular_probability
from ..render.envmap import Environment

MaterialFn = Callable[[Float[Tensor, "B 3"], Float[Tensor, "B 3"]], Material]
"""``(x, lookup_normal) -> Material`` at world surface points, given the hits' :attr:`SurfaceHit.lookup_normal`
(the fitted model's :func:`nefii.fit.model.decode_material`, or an analytic material in tests)."""

RR_MAX_SURVIVAL = 0.95


@dataclass(frozen=True)
class PathSettings:
    """What the path tracer follows."""

    max_bounces: int = 8
    """surface interactions per path; 1 = direct light only"""
    rr_depth: int = 3
    """Russian roulette decides after this many bounces"""
    f0: float = F0_DIELECTRIC
    """Fresnel reflectance at normal incidence (tests: 1 for a mirror)"""
    specular: bool = True
    """keep the GGX lobe (tests: off for a Lambertian white furnace)"""
    ray_offset: float = 1e-4
    """secondary and shadow rays start this far off the surface, relative to the geometry's size"""


@dataclass(frozen=True)
class PathRadiance:
    radiance: Float[Tensor, "P 3"]
    """radiance carried back along each primary ray; 0 where it misses the geometry"""
    hit: Bool[Tensor, " P"]
    """the primary ray hit the geometry"""


def _take(idx: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    return tuple(t[idx] for t in tensors)


@torch.no_grad()
def trace_paths(rays: Rays, geometry: Geometry, material: MaterialFn, env: Environment,
                generator: torch.Generator | None, settings: PathSettings = PathSettings()) -> PathRadiance:
    """One path per primary ray (``rays.origins``, ``rays.directions``: ``(P, 3)``, unit directions)."""
    if settings.max_bounces < 1:
        raise ValueError(f"max_bounces must be >= 1, got {settings.max_bounces}")
    o, d = rays.origins, rays.directions
    dev, dtype = o.device, o.dtype
    offset = settings.ray_offset * geometry.scale
    L = torch.zeros_like(o)                                  # radiance gathered per path
    first = geometry.intersect(Rays(o, d))

    # path state, compacted to the live paths: index, throughput, and the vertex x
    idx = first.valid.nonzero().squeeze(-1)                  # path of each live entry
    β = torch.ones(len(idx), 3, device=dev, dtype=dtype)     # path throughput
    x, n, ng, nl = _take(idx, first.position, first.normal, first.geometric_normal, first.lookup_normal)
    wo = -d[idx]                                             # towards the previous vertex

    for depth in range(settings.max_bounces):
        # ---- surface interaction: one-sided surfaces, shading frame, material
        front = dot(ng, wo) > 0
        idx, β, x, n, ng, nl, wo = _take(front, idx, β, x, n, ng, nl, wo)
        if len(idx) == 0:
            break
        m = material(x, nl)
        frame = Frame.from_normal(n)
        wo_l = frame.to_local(view_above_surface(n, wo))
        alpha = alpha_from_roughness(m.roughness)
        q = specular_probability(m, wo_l, settings.f0, settings.specular)
        u = torch.rand(len(idx), 6, generator=generator, device=dev, dtype=dtype)

        # ---- emitter sampling: next-event estimation with a shadow ray, MIS against BSDF sampling
        wl = env.sample_direction(u[:, 0:2])
        wl_l = frame.to_local(wl)
        p_l = env.pdf_direction(wl)
        p_b = pdf_bsdf(wo_l, wl_l, alpha, q)
        w_over_p = power_heuristic_over_pdf(p_l, torch.stack([p_l, p_b], -1))
        cos_l = wl_l[:, 2].clamp_min(0.0)
        contrib = β * f_r(m, wo_l, wl_l, settings.f0, settings.specular) * env.radiance(wl) \
            * (cos_l * w_over_p).unsqueeze(-1)
        lit = (contrib > 0).any(-1).nonzero().squeeze(-1)
        if len(lit):
            shadow = spawn_rays(x[lit], ng[lit], wl[lit], offset)
            seen = ~geometry.occluded(shadow)
            L.index_add_(0, idx[lit][seen], contrib[lit][seen])

        # ---- BSDF sampling: one direction from the cosine + GGX mixture
        wi_l = sample_bsdf(wo_l, alpha, q, u[:, 2:5])
        p_b = pdf_bsdf(wo_l, wi_l, alpha, q)
        weight = f_r(m, wo_l, wi_l, settings.f0, settings.specular) * (wi_l[:, 2].clamp_min(0.0)
                                                                      / p_b.clamp_min(1e-30)).unsqueeze(-1)
        β = β * torch.where((p_b > 0).unsqueeze(-1), weight, torch.zeros_like(weight))
        wi = frame.to_world(wi_l)
        alive = (β > 0).any(-1)
        idx, β, x, ng, wi, p_b, u = _take(alive, idx, β, x, ng, wi, p_b, u)
        if len(idx) == 0:
            break
        nxt = geometry.intersect(spawn_rays(x, ng, wi, offset))

        # ---- emission: the environment where the BSDF ray escapes, MIS against emitter sampling
        esc = ~nxt.valid
        if esc.any():
            p_b_esc, w_esc = p_b[esc], wi[esc]
            w_b = power_heuristic(p_b_esc, torch.stack([p_b_esc, env.pdf_direction(w_esc)], -1))
            L.index_add_(0, idx[esc], β[esc] * env.radiance(w_esc) * w_b.unsqueeze(-1))

        # ---- stopping: the path goes on where the ray hit, past Russian roulette
        go_on = nxt.valid
        if depth + 1 >= settings.rr_depth:
            q_rr = β.amax(-1).clamp(max=RR_MAX_SURVIVAL)
            go_on = go_on & (u[:, 5] < q_rr)
            β = β / q_rr.clamp_min(1e-30).unsqueeze(-1)
        idx, β, wi = _take(go_on, idx, β, wi)
        x, n, ng, nl = _take(go_on, nxt.position, nxt.normal, nxt.geometric_normal, nxt.lookup_normal)
        wo = -wi

    return PathRadiance(radiance=L, hit=first.valid)
