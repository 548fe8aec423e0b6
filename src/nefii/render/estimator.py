"""Monte Carlo estimate of the rendering equation at surface points (paper Eq. 1-3).

    L_o(x, wo) ~= 1/N sum_{i=1..N} sum_{s in {cos, ggx, sg}} w_s(wi_s) L_i(x, wi_s) f_r(x, wo, wi_s) (wi_s . n) / p_s(wi_s)

One estimator sample draws one direction from each of the three strategies (cosine,
GGX visible normals, SG mixture) and fuses them with the power heuristic, as the
official code does; ``N`` estimator samples make ``3N`` directions per point.

What it does: directions and MIS weights for a batch of points (:func:`sample_mis_directions`),
then the weighted sum for whatever incoming radiance the caller traced along them
(:func:`combine`); :func:`estimate_Lo` does both for an ``incoming`` callable.
What it does not: trace rays or decide what ``L_i`` is (``V E(w)`` or the radiance cache:
the caller does), and it does not differentiate through the sampling. Directions and
weights are drawn without gradient, so the gradient of the estimate is the estimate of
the gradient of the integrand (parameters reach it through ``f_r`` and ``L_i``).

Shapes: ``*bs`` shading points, ``S = 3N`` directions per point.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from jaxtyping import Float
from torch import Tensor

from .brdf import F0_DIELECTRIC, Material, alpha_from_roughness, brdf_eval
from .frame import Frame, dot, normalize
from .mis import power_heuristic_over_pdf
from .lights import LightSampler, SGLightSampler, as_light_sampler
from .samplers import pdf_cosine, pdf_ggx_vndf, sample_cosine, sample_ggx_vndf
from .sg import SGMixture

IncomingRadiance = Callable[[Float[Tensor, "*bs S 3"]], Float[Tensor, "*bs S 3"]]
"""``wi -> L_i(x, wi)``: radiance arriving at each shading point from each direction."""

MIN_COS_VIEW = 1e-4


@dataclass(frozen=True)
class DirectionSamples:
    """Incident directions at a batch of shading points and the factor each contributes with."""

    wi: Float[Tensor, "*bs S 3"]
    """unit world directions towards the light"""
    weight: Float[Tensor, "*bs S"]
    """MIS weight over pdf, ``w_s(wi) / p_s(wi)``; 0 for directions below the surface"""
    wo: Float[Tensor, "*bs 3"]
    """the view direction actually shaded (moved just above the surface if it was not)"""
    num_estimator_samples: int
    """N: the sum over the S directions is divided by N"""
    light_lobes: Float[Tensor, "*bs S K"] | None = None
    """with an SG light strategy, its unit lobe values ``sg_lobes(wi, sg)`` (computed for the light pdf; the
    radiance of a direction that escapes is these times the amplitudes); None for other light samplers"""


@dataclass(frozen=True)
class RadianceEstimate:
    """Outgoing radiance ``L_o(x, wo)`` split by BRDF lobe."""

    diffuse: Float[Tensor, "*bs 3"]
    specular: Float[Tensor, "*bs 3"]

    @property
    def rgb(self) -> Float[Tensor, "*bs 3"]:
        return self.diffuse + self.specular


def view_above_surface(n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """``wo`` with its normal component raised to at least ``MIN_COS_VIEW``.

    Interpolated shading normals can face slightly away from the camera at silhouettes;
    the BRDF and the visible-normal sampler both need ``wo . n > 0``.
    """
    cos = dot(n, wo).unsqueeze(-1)
    return normalize(wo + (MIN_COS_VIEW - cos).clamp_min(0.0) * n)


def _uniform(shape: tuple[int, ...], like: Tensor, generator: torch.Generator | None) -> Tensor:
    return torch.rand(shape, generator=generator, device=like.device, dtype=like.dtype)


@torch.no_grad()
def sample_mis_directions(n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"], roughness: Float[Tensor, " *bs"],
                          light: SGMixture | LightSampler, num_samples: int,
                          generator: torch.Generator | None = None) -> DirectionSamples:
    """``num_samples`` estimator samples per point, each one direction per strategy (S = 3N).

    Directions are ordered ``[cosine x N | GGX x N | light x N]`` along the S axis. The light
    strategy is the SG mixture of Eq. 5-6 for an :class:`SGMixture`, or any
    :class:`~nefii.render.lights.LightSampler` (e.g. an env map's piecewise-constant 2D sampling).
    """
    light = as_light_sampler(light)
    bs, N = n.shape[:-1], num_samples
    frame = Frame.from_normal(n)
    wo = view_above_surface(n, wo)
    wo_local = frame.to_local(wo).unsqueeze(-2)                   # (*bs, 1, 3)
    alpha = alpha_from_roughness(roughness).unsqueeze(-1)          # (*bs, 1)
    frame_s = frame.unsqueeze(-2)

    # ---- one direction from each strategy
    wi_cos = frame_s.to_world(sample_cosine(_uniform((*bs, N, 2), n, generator)))
    wi_ggx = frame_s.to_world(sample_ggx_vndf(wo_local, alpha,
                                              _uniform((*bs, N, 2), n, generator)))
    wi_light = light.sample(n, _uniform((*bs, N, 3), n, generator))
    wi = normalize(torch.cat([wi_cos, wi_ggx, wi_light], -2))     # (*bs, 3N, 3)

    # ---- every strategy's density at every direction
    wi_local = frame_s.to_local(wi)
    if isinstance(light, SGLightSampler):
        p_light, lobes = light.pdf_and_lobes(n, wi)
    else:
        p_light, lobes = light.pdf(n, wi), None
    p_all = torch.stack([pdf_cosine(wi_local), pdf_ggx_vndf(wo_local, wi_local, alpha), p_light], -1)  # (*bs, 3N, 3)
    own = torch.arange(3, device=n.device).repeat_interleave(N)   # strategy of each direction
    p_own = p_all.gather(-1, own.expand(*bs, 3 * N).unsqueeze(-1)).squeeze(-1)

    # ---- power heuristic; directions under the surface carry nothing
    weight = power_heuristic_over_pdf(p_own, p_all)
    weight = torch.where(wi_local[..., 2] > 0, weight, torch.zeros_like(weight))
    return DirectionSamples(wi=wi, weight=weight, wo=wo, num_estimator_samples=N, light_lobes=lobes)


def _terms(samples: DirectionSamples, material: Material, n: Float[Tensor, "*bs 3"], L_i: Float[Tensor, "*bs S 3"],
           f0: float | Tensor) -> tuple[Float[Tensor, "*bs S 3"], Float[Tensor, "*bs S 3"]]:
    """Per-direction ``weight f_r L_i (wi . n)`` of the diffuse and specular lobes (not yet divided by N)."""
    m = Material(material.albedo.unsqueeze(-2), material.roughness.unsqueeze(-1), material.brdf)
    n_s = n.unsqueeze(-2)
    f = brdf_eval(m, n_s, samples.wo.unsqueeze(-2), samples.wi, f0)
    c = (samples.weight * dot(n_s, samples.wi).clamp_min(0.0)).unsqueeze(-1)
    return f.diffuse * L_i * c, f.specular * L_i * c


def combine(samples: DirectionSamples, material: Material, n: Float[Tensor, "*bs 3"],
            L_i: Float[Tensor, "*bs S 3"], f0: float | Tensor = F0_DIELECTRIC) -> RadianceEstimate:
    """The estimator's sum: ``1/N sum_S weight f_r L_i (wi . n)``, per lobe."""
    diffuse, specular = _terms(samples, material, n, L_i, f0)
    N = samples.num_estimator_samples
    return RadianceEstimate(diffuse=diffuse.sum(-2) / N, specular=specular.sum(-2) / N)


def combine_pair(samples: DirectionSamples, material: Material, n: Float[Tensor, "*bs 3"],
                 L_i: Float[Tensor, "*bs S 3"], f0: float | Tensor = F0_DIELECTRIC
                 ) -> tuple[RadianceEstimate, RadianceEstimate]:
    """Two independent estimates from the first ``N // 2`` and the other ``N - N // 2`` estimator samples.

    Each is unbiased on its own and their sample-count-weighted mean is :func:`combine`'s estimate.
    Products of their errors estimate squared errors of the mean without the variance term that
    the square of one noisy estimate carries (see ``nefii.fit.losses``). Needs ``N >= 2``.
    """
    N = samples.num_estimator_samples
    if N < 2:
        raise ValueError(f"two independent estimates need N >= 2 estimator samples, got {N}")
    diffuse, specular = _terms(samples, material, n, L_i, f0)
    first = (torch.arange(3 * N, device=n.device) % N) < N // 2              # estimator sample i owns i, N+i, 2N+i
    halves = []
    for mask, count in ((first, N // 2), (~first, N - N // 2)):
        m = mask.to(diffuse.dtype).unsqueeze(-1)
        halves.append(RadianceEstimate(diffuse=(diffuse * m).sum(-2) / count, specular=(specular * m).sum(-2) / count))
    return halves[0], halves[1]


def mean_of_pair(pair: tuple[RadianceEstimate, RadianceEstimate], num_samples: int) -> RadianceEstimate:
    """:func:`combine`'s estimate from :func:`combine_pair`'s two halves (weighted by their sample counts)."""
    a, b = pair
    wa, wb = (num_samples // 2) / num_samples, (num_samples - num_samples // 2) / num_samples
    return RadianceEstimate(diffuse=wa * a.diffuse + wb * b.diffuse, specular=wa * a.specular + wb * b.specular)


def estimate_Lo(n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"], material: Material,
                light: SGMixture | LightSampler, incoming: IncomingRadiance, num_samples: int,
                generator: torch.Generator | None = None, f0: float | Tensor = F0_DIELECTRIC) -> RadianceEstimate:
    """Eq. 2 by MIS of cosine, GGX-VNDF and light sampling, for incoming radiance ``incoming(wi)``."""
    samples = sample_mis_directions(n, wo, material.roughness.detach(), light, num_samples, generator)
    return combine(samples, material, n, incoming(samples.wi), f0)
