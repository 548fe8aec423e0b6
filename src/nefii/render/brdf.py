"""The simplified Disney BRDF of the paper: a diffuse lobe plus a GGX microfacet lobe.

``f_r = albedo / pi * d + F D G / (4 (n.l)(n.v))`` with

* ``D``: GGX (Trowbridge-Reitz) with ``alpha = roughness^2``;
* ``F``: Schlick with ``F0 = 0.04`` (specular 0.5 in Disney terms: ``0.16 * 0.5^2``);
* ``G`` (:attr:`BRDFModel.shadowing`): ``smith``, the exact separable Smith term of GGX,
  ``G1(x) = 2x / (x + sqrt(alpha^2 + (1 - alpha^2) x^2))``, or ``schlick``, the official code's
  Schlick-GGX ``G1(x) = x / (x (1-k) + k)`` with ``k = (roughness + 1)^2 / 8``;
* ``d`` (:attr:`BRDFModel.diffuse`): ``lambert`` (1, the official code) or ``burley``, the Disney
  diffuse with its roughness-dependent retro-reflection,
  ``(1 - F_L/2)(1 - F_V/2) + R (F_L + F_V + F_L F_V (R - 1))``, ``F_x = (1 - x)^5``, ``R = 2 r (l.h)^2``.

The official code's pair (lambert, schlick) is :data:`OFFICIAL_BRDF`. ``k = (r+1)^2/8`` is Karis's
remapping for point lights; under an environment it over-shadows rough lobes, and a fit then lowers
roughness to win the energy back: at the true material, light and transport, roughness freed alone
drifts 0.47 glossy on the cup's rough parts (docs/experiments.md, 2026-11-25). Renderers and measured
materials use the exact Smith term and a Burley-like diffuse, so they are the default
(:class:`BRDFModel`); the ``paper`` preset keeps the official pair.

Each factor is its own function over cosines; :func:`brdf_eval` composes them.
Shapes: ``*bs`` any batch; roughness and cosines have no channel axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import torch
from jaxtyping import Float
from torch import Tensor

from ..config_tools import validate
from .frame import dot, normalize

F0_DIELECTRIC = 0.16 * 0.5**2
"""Specular reflectance at normal incidence: 0.04."""
ROUGHNESS_MIN = 0.089
ROUGHNESS_RANGE = 0.911
"""The official code maps a network output s to roughness 0.911 sigmoid(s) + 0.089."""


@dataclass(frozen=True)
class BRDFModel:
    """Which diffuse lobe and which shadowing-masking term :func:`brdf_eval` uses."""

    diffuse: Literal["burley", "lambert"] = "burley"
    """``burley``: Disney diffuse with retro-reflection; ``lambert``: ``albedo / pi`` (official code)"""
    shadowing: Literal["smith", "schlick"] = "smith"
    """``smith``: exact separable Smith for GGX; ``schlick``: Schlick-GGX, k = (r+1)^2/8 (official code)"""

    def __post_init__(self) -> None:
        validate(self)


OFFICIAL_BRDF = BRDFModel(diffuse="lambert", shadowing="schlick")
"""The official NeFII code's BRDF: Lambert diffuse, Schlick-GGX shadowing."""


@dataclass(frozen=True)
class Material:
    """BRDF parameters at a batch of surface points, and the BRDF that reads them."""

    albedo: Float[Tensor, "*bs 3"]
    """diffuse albedo, linear RGB in [0, 1]"""
    roughness: Float[Tensor, " *bs"]
    """perceptual roughness r in [0.089, 1]; GGX alpha = r^2"""
    brdf: BRDFModel = field(default_factory=BRDFModel)
    """the lobes these parameters feed"""


@dataclass(frozen=True)
class BRDFValue:
    """``f_r`` split into its lobes (no cosine factor)."""

    diffuse: Float[Tensor, "*bs 3"]
    specular: Float[Tensor, "*bs 3"]

    @property
    def total(self) -> Float[Tensor, "*bs 3"]:
        return self.diffuse + self.specular


def roughness_from_logit(s: Tensor) -> Tensor:
    """The official code's roughness activation ``0.911 sigmoid(s) + 0.089``."""
    return ROUGHNESS_RANGE * torch.sigmoid(s) + ROUGHNESS_MIN


def alpha_from_roughness(roughness: Tensor) -> Tensor:
    """GGX alpha = roughness^2."""
    return roughness * roughness


def D_ggx(n_dot_h: Float[Tensor, "*bs"], alpha: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs"]:
    """GGX normal distribution ``alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)``, 0 below the horizon."""
    a2 = alpha * alpha
    c = n_dot_h.clamp_min(0.0)
    denom = c * c * (a2 - 1.0) + 1.0
    return torch.where(n_dot_h > 0, a2 / (math.pi * denom * denom), torch.zeros_like(denom))


def F_schlick(v_dot_h: Float[Tensor, "*bs"], f0: float | Tensor = F0_DIELECTRIC) -> Float[Tensor, "*bs"]:
    """Schlick's Fresnel ``F0 + (1 - F0)(1 - v.h)^5``."""
    return f0 + (1.0 - f0) * (1.0 - v_dot_h.clamp(0.0, 1.0)) ** 5


def k_schlick(roughness: Tensor) -> Tensor:
    """Schlick-GGX remapping ``k = (r + 1)^2 / 8``."""
    return (roughness + 1.0) ** 2 / 8.0


def G1_schlick_ggx(n_dot_x: Float[Tensor, "*bs"], k: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs"]:
    """``x / (x (1 - k) + k)`` for ``x = n.l`` or ``n.v`` (clamped to >= 0)."""
    c = n_dot_x.clamp_min(0.0)
    return c / (c * (1.0 - k) + k)


def G_smith(n_dot_l: Tensor, n_dot_v: Tensor, roughness: Tensor) -> Tensor:
    """Separable Smith shadowing-masking ``G1(n.l) G1(n.v)`` with Schlick-GGX G1."""
    k = k_schlick(roughness)
    return G1_schlick_ggx(n_dot_l, k) * G1_schlick_ggx(n_dot_v, k)


def V_smith(n_dot_l: Tensor, n_dot_v: Tensor, roughness: Tensor) -> Tensor:
    """``G / (4 (n.l)(n.v))`` in the form that has no 0/0: ``1 / (4 (l(1-k)+k)(v(1-k)+k))``."""
    k = k_schlick(roughness)
    nl = n_dot_l.clamp_min(0.0)
    nv = n_dot_v.clamp_min(0.0)
    return 0.25 / ((nl * (1.0 - k) + k) * (nv * (1.0 - k) + k))


def V_smith_ggx(n_dot_l: Tensor, n_dot_v: Tensor, roughness: Tensor) -> Tensor:
    """``G1(n.l) G1(n.v) / (4 (n.l)(n.v))`` with the exact GGX ``G1`` (:func:`G1_smith_ggx`), written without
    0/0: ``1 / ((l + sqrt(a^2 + (1-a^2) l^2)) (v + sqrt(a^2 + (1-a^2) v^2)))``, ``a = alpha``."""
    a2 = alpha_from_roughness(roughness) ** 2
    nl = n_dot_l.clamp_min(0.0)
    nv = n_dot_v.clamp_min(0.0)
    return 1.0 / ((nl + (a2 + (1.0 - a2) * nl * nl).sqrt()) * (nv + (a2 + (1.0 - a2) * nv * nv).sqrt()))


def burley_factor(n_dot_l: Tensor, n_dot_v: Tensor, l_dot_h: Tensor, roughness: Tensor) -> Tensor:
    """Disney diffuse over Lambert: ``(1 - F_L/2)(1 - F_V/2) + R (F_L + F_V + F_L F_V (R - 1))`` with
    ``F_x = (1 - x)^5`` and ``R = 2 r (l.h)^2`` (Burley 2015; equal to the 2012 form
    ``(1 + (F_D90 - 1) F_L)(1 + (F_D90 - 1) F_V)``, ``F_D90 = 1/2 + R``). 1 at normal incidence."""
    fl = (1.0 - n_dot_l.clamp(0.0, 1.0)) ** 5
    fv = (1.0 - n_dot_v.clamp(0.0, 1.0)) ** 5
    rr = 2.0 * roughness * l_dot_h.clamp(0.0, 1.0) ** 2
    return (1.0 - 0.5 * fl) * (1.0 - 0.5 * fv) + rr * (fl + fv + fl * fv * (rr - 1.0))


def G1_smith_ggx(n_dot_v: Float[Tensor, "*bs"], alpha: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs"]:
    """Exact Smith masking for GGX: ``2 c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2))``, c = n.v > 0."""
    c = n_dot_v.clamp_min(0.0)
    a2 = alpha * alpha
    return 2.0 * c / (c + (a2 + (1.0 - a2) * c * c).sqrt()).clamp_min(1e-30)


def brdf_eval(material: Material, n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"],
              wi: Float[Tensor, "*bs 3"], f0: float | Tensor = F0_DIELECTRIC) -> BRDFValue:
    """``f_r(x, wo, wi)`` for unit ``n``, ``wo`` (towards the viewer), ``wi`` (towards the light).

    The lobes are those of ``material.brdf``. Zero unless both ``wo`` and ``wi`` are above the surface.
    Broadcasts over ``*bs``.
    """
    n_dot_l = dot(n, wi)
    n_dot_v = dot(n, wo)
    h = normalize(wi + wo)
    r = material.roughness
    model = material.brdf
    D = D_ggx(dot(n, h), alpha_from_roughness(r))
    F = F_schlick(dot(wo, h), f0)
    V = V_smith_ggx(n_dot_l, n_dot_v, r) if model.shadowing == "smith" else V_smith(n_dot_l, n_dot_v, r)
    spec = (F * D * V).unsqueeze(-1)
    above = ((n_dot_l > 0) & (n_dot_v > 0)).unsqueeze(-1)
    zero = torch.zeros((), dtype=spec.dtype, device=spec.device)
    diffuse = material.albedo / math.pi
    if model.diffuse == "burley":
        diffuse = diffuse * burley_factor(n_dot_l, n_dot_v, dot(wi, h), r).unsqueeze(-1)
    diffuse = torch.where(above, diffuse, zero)
    specular = torch.where(above, spec.expand(diffuse.shape), zero)
    return BRDFValue(diffuse=diffuse, specular=specular)
