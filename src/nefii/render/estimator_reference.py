"""The deliberately simple estimator of Eq. 2: cosine-weighted sampling only, no MIS.

It exists to test :mod:`nefii.render.estimator` against: both must agree in mean.
Each of the N samples has weight ``1 / p(wi) = pi / (wi . n)``.
"""
from __future__ import annotations


import torch
from jaxtyping import Float
from torch import Tensor

from .brdf import F0_DIELECTRIC, Material
from .estimator import DirectionSamples, IncomingRadiance, RadianceEstimate, combine, view_above_surface
from .frame import Frame
from .samplers import pdf_cosine, sample_cosine


@torch.no_grad()
def sample_cosine_directions(n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"], num_samples: int,
                             generator: torch.Generator | None = None) -> DirectionSamples:
    """``num_samples`` cosine-weighted directions per point with weight ``1 / pdf``."""
    u = torch.rand((*n.shape[:-1], num_samples, 2), generator=generator, device=n.device, dtype=n.dtype)
    local = sample_cosine(u)
    pdf = pdf_cosine(local)
    weight = torch.where(pdf > 0, 1.0 / pdf.clamp_min(1e-30), torch.zeros_like(pdf))
    wi = Frame.from_normal(n).unsqueeze(-2).to_world(local)
    return DirectionSamples(wi=wi, weight=weight, wo=view_above_surface(n, wo), num_estimator_samples=num_samples)


def estimate_Lo_reference(n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"], material: Material,
                          incoming: IncomingRadiance, num_samples: int, generator: torch.Generator | None = None,
                          f0: float | Tensor = F0_DIELECTRIC) -> RadianceEstimate:
    """Eq. 2 with cosine sampling only."""
    samples = sample_cosine_directions(n, wo, num_samples, generator)
    return combine(samples, material, n, incoming(samples.wi), f0)


