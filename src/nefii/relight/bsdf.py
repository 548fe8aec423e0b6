"""The BRDF as the path tracer uses it: evaluation, and one sampled continuation direction.

BSDF sampling draws **one** direction per path vertex from the mixture

    p_bsdf(wi) = (1 - q) p_cos(wi) + q p_ggx(wi | wo)

of the cosine-weighted hemisphere (for the diffuse lobe) and the GGX visible normals reflected
about ``wo`` (for the specular lobe, Heitz 2018), both from :mod:`nefii.render.samplers`, with
the specular lobe chosen with probability ``q = clamp(F(n.wo) / (F(n.wo) + mean(albedo)), 0.2, 0.9)``,
its rough share of reflected energy. ``q`` depends on the vertex only, never on the sampled
direction, so ``p_bsdf`` is the density of exactly what :func:`sample_bsdf` returns (a direction
below the surface, which GGX sometimes gives, is a valid sample that carries nothing).

All directions are in the local shading frame (``n = +z``). ``f0`` (Fresnel at normal incidence)
and ``specular`` (keep the GGX lobe) exist for tests: a mirror with ``f0 = 1``, a Lambertian
white furnace with ``specular = False``.
"""
from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from ..render.brdf import F0_DIELECTRIC, F_schlick, Material, brdf_eval
from ..render.samplers import pdf_cosine, pdf_ggx_vndf, sample_cosine, sample_ggx_vndf

Q_SPECULAR_RANGE = (0.2, 0.9)
"""bounds of the specular lobe's selection probability (when the lobe is on)"""


def f_r(material: Material, wo: Float[Tensor, "*bs 3"], wi: Float[Tensor, "*bs 3"],
        f0: float = F0_DIELECTRIC, specular: bool = True) -> Float[Tensor, "*bs 3"]:
    """``f_r(wo, wi)`` of the simplified Disney BRDF, local frame; the diffuse lobe alone without ``specular``."""
    n = torch.zeros_like(wo)
    n[..., 2] = 1.0
    value = brdf_eval(material, n, wo, wi, f0)
    return value.total if specular else value.diffuse


def specular_probability(material: Material, wo: Float[Tensor, "*bs 3"], f0: float = F0_DIELECTRIC,
                         specular: bool = True) -> Float[Tensor, " *bs"]:
    """``q``: the chance of sampling the GGX lobe at this vertex (0 without the specular lobe)."""
    if not specular:
        return torch.zeros_like(wo[..., 2])
    F = F_schlick(wo[..., 2], f0)
    q = F / (F + material.albedo.mean(-1)).clamp_min(1e-12)
    return q.clamp(*Q_SPECULAR_RANGE)


def sample_bsdf(wo: Float[Tensor, "*bs 3"], alpha: Float[Tensor, " *bs"], q: Float[Tensor, " *bs"],
                u: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """A direction from the mixture: GGX where ``u[..., 0] < q``, else cosine (from ``u[..., 1:]``)."""
    w_cos = sample_cosine(u[..., 1:])
    w_ggx = sample_ggx_vndf(wo, alpha, u[..., 1:])
    return torch.where((u[..., 0] < q).unsqueeze(-1), w_ggx, w_cos)


def pdf_bsdf(wo: Float[Tensor, "*bs 3"], wi: Float[Tensor, "*bs 3"], alpha: Float[Tensor, " *bs"],
             q: Float[Tensor, " *bs"]) -> Float[Tensor, " *bs"]:
    """Density over solid angle of :func:`sample_bsdf`, on the whole sphere."""
    return (1.0 - q) * pdf_cosine(wi) + q * pdf_ggx_vndf(wo, wi, alpha)
