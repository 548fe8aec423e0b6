"""The BRDF of nefii.render.brdf: closed forms, normalisation by quadrature, furnaces, gradients.

Quadratures are float64 graded Gauss-Legendre rules (tests/quadrature.py) centred on where the
integrand is sharp, so that GGX with alpha = 0.089^2 is resolved.
"""
from __future__ import annotations

import math

import pytest
import torch

from quadrature import DTYPE, integrate_upper_hemisphere, orthonormal_frame
from nefii.render.brdf import (F0_DIELECTRIC, OFFICIAL_BRDF, ROUGHNESS_MIN, BRDFModel, D_ggx, F_schlick,
                               G1_smith_ggx, G_smith, Material, V_smith, V_smith_ggx, brdf_eval, burley_factor,
                               roughness_from_logit)
from nefii.render.estimator import estimate_Lo
from nefii.render.estimator_reference import estimate_Lo_reference
from nefii.render.sg import SGMixture, sg_eval, sg_lobes

ALPHAS = (ROUGHNESS_MIN**2, 0.02, 0.1, 0.36, 1.0)
MODELS = (BRDFModel(), OFFICIAL_BRDF, BRDFModel("lambert", "smith"), BRDFModel("burley", "schlick"))
LAMBERT = BRDFModel(diffuse="lambert")
UP = torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE)


def tensor(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=DTYPE)


def unit(*values: float) -> torch.Tensor:
    v = tensor(*values)
    return v / v.norm()


def local_view(view_deg: float, azimuth: float = 0.7) -> torch.Tensor:
    theta = math.radians(view_deg)
    return tensor(math.sin(theta) * math.cos(azimuth), math.sin(theta) * math.sin(azimuth), math.cos(theta))


def random_upper(n: int, gen: torch.Generator, min_cos: float = 0.05) -> torch.Tensor:
    """Random unit vectors with z in [min_cos, 1)."""
    z = min_cos + (1.0 - min_cos) * torch.rand(n, generator=gen, dtype=DTYPE)
    phi = 2.0 * math.pi * torch.rand(n, generator=gen, dtype=DTYPE)
    r = (1.0 - z * z).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


# --------------------------------------------------------------------------- normalisation


@pytest.mark.parametrize("alpha", ALPHAS)
def test_ggx_D_is_normalised(alpha: float) -> None:
    """``int D(h) (n.h) dh = 1`` over the hemisphere (projected microfacet area is the macro-surface)."""
    a = tensor(alpha)[0]
    total = integrate_upper_hemisphere(lambda h: D_ggx(h[..., 2], a) * h[..., 2], UP, eps=1e-3 * alpha**2)
    assert total == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("view_deg", (0.0, 45.0, 85.0, 89.9))
@pytest.mark.parametrize("alpha", ALPHAS)
def test_visible_normal_distribution_is_normalised(alpha: float, view_deg: float) -> None:
    """``int G1(wo) max(0, wo.h) D(h) / wo.z dh = 1``: the exact Smith G1 is the normaliser of D's visible normals."""
    a, wo = tensor(alpha)[0], local_view(view_deg)
    def d_wo(h):
        return G1_smith_ggx(wo[2], a) * (h @ wo).clamp_min(0.0) * D_ggx(h[..., 2], a) / wo[2]
    assert integrate_upper_hemisphere(d_wo, UP, eps=1e-3 * alpha**2) == pytest.approx(1.0, abs=1e-5)


def test_G1_smith_ggx_closed_form() -> None:
    """``G1 = 1 / (1 + Lambda)``, ``Lambda = (sqrt(1 + alpha^2 tan^2) - 1) / 2``; 1 at normal incidence, 0 grazing."""
    gen = torch.Generator().manual_seed(3)
    c = 0.01 + 0.99 * torch.rand(64, generator=gen, dtype=DTYPE)
    a = 0.005 + torch.rand(64, generator=gen, dtype=DTYPE)
    tan2 = (1.0 - c * c) / (c * c)
    torch.testing.assert_close(G1_smith_ggx(c, a), 2.0 / (1.0 + (1.0 + a * a * tan2).sqrt()), rtol=1e-12, atol=0.0)
    assert torch.allclose(G1_smith_ggx(torch.ones(3, dtype=DTYPE), tensor(0.01, 0.3, 1.0)), torch.ones(3, dtype=DTYPE))
    assert torch.equal(G1_smith_ggx(torch.zeros(2, dtype=DTYPE), tensor(0.3, 1.0)), torch.zeros(2, dtype=DTYPE))


# --------------------------------------------------------------------------- closed forms


def test_V_smith_is_G_over_4_nl_nv() -> None:
    gen = torch.Generator().manual_seed(1)
    nl = 1e-3 + torch.rand(256, generator=gen, dtype=DTYPE)
    nv = 1e-3 + torch.rand(256, generator=gen, dtype=DTYPE)
    r = ROUGHNESS_MIN + (1.0 - ROUGHNESS_MIN) * torch.rand(256, generator=gen, dtype=DTYPE)
    nl, nv = nl.clamp_max(1.0), nv.clamp_max(1.0)
    torch.testing.assert_close(V_smith(nl, nv, r), G_smith(nl, nv, r) / (4.0 * nl * nv), rtol=1e-12, atol=0.0)


def test_V_smith_ggx_is_exact_G_over_4_nl_nv() -> None:
    """The exact shadowing term: ``G1_smith_ggx(nl) G1_smith_ggx(nv) / (4 nl nv)`` with alpha = r^2."""
    gen = torch.Generator().manual_seed(2)
    nl = (1e-3 + torch.rand(256, generator=gen, dtype=DTYPE)).clamp_max(1.0)
    nv = (1e-3 + torch.rand(256, generator=gen, dtype=DTYPE)).clamp_max(1.0)
    r = ROUGHNESS_MIN + (1.0 - ROUGHNESS_MIN) * torch.rand(256, generator=gen, dtype=DTYPE)
    want = G1_smith_ggx(nl, r * r) * G1_smith_ggx(nv, r * r) / (4.0 * nl * nv)
    torch.testing.assert_close(V_smith_ggx(nl, nv, r), want, rtol=1e-12, atol=0.0)


def test_burley_factor_is_the_2012_form() -> None:
    """Burley 2015's ``(1 - F_L/2)(1 - F_V/2) + R (F_L + F_V + F_L F_V (R - 1))`` equals Burley 2012's
    ``(1 + (F_D90 - 1) F_L)(1 + (F_D90 - 1) F_V)`` with ``F_D90 = 1/2 + 2 r (l.h)^2``; 1 at normal incidence."""
    gen = torch.Generator().manual_seed(9)
    nl, nv, lh, r = (torch.rand(256, generator=gen, dtype=DTYPE) for _ in range(4))
    fd90 = 0.5 + 2.0 * r * lh * lh
    want = (1 + (fd90 - 1) * (1 - nl) ** 5) * (1 + (fd90 - 1) * (1 - nv) ** 5)
    torch.testing.assert_close(burley_factor(nl, nv, lh, r), want, rtol=1e-12, atol=1e-15)
    one = torch.ones(3, dtype=DTYPE)
    torch.testing.assert_close(burley_factor(one, one, one, tensor(0.1, 0.5, 1.0)), one, rtol=0.0, atol=1e-15)


@pytest.mark.parametrize("roughness", (0.089, 0.5, 1.0))
def test_burley_directional_albedo_at_normal_view(roughness: float) -> None:
    """Seen along the normal, ``F_V = 0`` and ``l.h = cos(theta_l / 2)``, so the white Burley lobe returns
    ``1 + 2 int_0^1 (r (1 + mu) - 1/2)(1 - mu)^5 mu dmu = 1 + 5 r / 84 - 1 / 42`` (Beta integrals)."""
    m = Material(torch.ones(3, dtype=DTYPE), tensor(roughness)[0], BRDFModel(diffuse="burley"))
    albedo = integrate_upper_hemisphere(lambda w: brdf_eval(m, UP, UP, w).diffuse[..., 0] * w[..., 2], UP)
    assert albedo == pytest.approx(1.0 + 5.0 * roughness / 84.0 - 1.0 / 42.0, abs=1e-6)


def test_G_smith_is_the_schlick_ggx_product() -> None:
    """``G1(x) = x / (x (1 - k) + k)`` with ``k = (r + 1)^2 / 8`` for both directions (docs/design.md)."""
    nl, nv, r = tensor(0.3, 0.9), tensor(0.7, 0.2), tensor(0.5, 1.0)
    k = (r + 1.0) ** 2 / 8.0
    want = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
    torch.testing.assert_close(G_smith(nl, nv, r), want, rtol=1e-14, atol=0.0)


@pytest.mark.parametrize("f0", (F0_DIELECTRIC, 0.5, 1.0))
def test_F_schlick_limits(f0: float) -> None:
    """F0 at normal incidence, 1 at grazing, monotone in between."""
    c = torch.linspace(0.0, 1.0, 101, dtype=DTYPE)
    F = F_schlick(c, f0)
    assert float(F[-1]) == pytest.approx(f0, abs=1e-15)
    assert float(F[0]) == pytest.approx(1.0, abs=1e-15)
    assert bool((F[1:] <= F[:-1]).all())
    torch.testing.assert_close(F, f0 + (1 - f0) * (1 - c) ** 5, rtol=1e-14, atol=1e-15)


def test_F0_dielectric_is_0_04() -> None:
    assert F0_DIELECTRIC == pytest.approx(0.04, rel=1e-12)


def test_roughness_from_logit_spans_the_official_range() -> None:
    s = torch.linspace(-60.0, 60.0, 2001, dtype=DTYPE)
    r = roughness_from_logit(s)
    assert bool((r >= 0.089).all()) and bool((r <= 1.0).all())
    assert bool((r[1:] >= r[:-1]).all())
    assert float(r[0]) == pytest.approx(0.089, abs=1e-12)
    assert float(r[-1]) == pytest.approx(1.0, abs=1e-12)
    assert float(roughness_from_logit(tensor(0.0))) == pytest.approx(0.089 + 0.911 / 2, abs=1e-15)


# --------------------------------------------------------------------------- furnaces

FURNACE_ENV = SGMixture(torch.stack([unit(0.1, 0.2, 1.0), unit(1.0, -0.3, 0.2), unit(-0.4, 0.6, -0.5)]),
                        tensor(2.0, 40.0, 10.0),
                        torch.stack([tensor(1.0, 1.0, 1.0), tensor(8.0, 6.0, 4.0), tensor(2.0, 2.0, 2.0)]))
"""Only the SG strategy of the MIS estimator looks at it: the incoming radiance of a furnace is 1."""
FURNACE_NORMAL = unit(0.3, -0.2, 0.93)


def world_view(n: torch.Tensor, view_deg: float) -> torch.Tensor:
    """A unit ``wo`` at ``view_deg`` from ``n``."""
    n_, e1, e2 = orthonormal_frame(n)
    theta = math.radians(view_deg)
    return math.cos(theta) * n_ + math.sin(theta) * (0.6 * e1 + 0.8 * e2)


@pytest.mark.parametrize("view_deg", (0.0, 60.0, 89.0))
def test_white_lambertian_furnace_by_quadrature(view_deg: float) -> None:
    """``int (albedo / pi) cos dwi = 1`` for albedo 1 (diffuse part of ``brdf_eval``, Lambert lobe)."""
    local = Material(torch.ones(3, dtype=DTYPE), tensor(0.5)[0], LAMBERT)
    wo = local_view(view_deg)
    Lo = integrate_upper_hemisphere(lambda w: brdf_eval(local, UP, wo, w).diffuse[..., 1] * w[..., 2], UP)
    assert Lo == pytest.approx(1.0, abs=1e-3)


def per_point_mean_and_se(x: torch.Tensor) -> tuple[float, float]:
    return float(x.mean()), float(x.std() / math.sqrt(x.shape[0]))


@pytest.mark.parametrize("view_deg", (0.0, 60.0, 85.0))
@pytest.mark.parametrize("roughness", (0.089, 0.5, 1.0))
def test_white_lambertian_furnace_by_estimators(roughness: float, view_deg: float) -> None:
    """Incoming radiance 1 on a white Lambertian: both estimators give diffuse radiance 1.

    The MIS estimate agrees within 4 standard errors (over 4000 independent points). The
    cosine-only reference has zero variance here (``f cos / p = 1`` for every sample).
    """
    B, N = 4000, 4
    n = FURNACE_NORMAL.expand(B, 3)
    wo = world_view(FURNACE_NORMAL, view_deg).expand(B, 3)
    material = Material(torch.ones(B, 3, dtype=DTYPE), torch.full((B,), roughness, dtype=DTYPE), LAMBERT)
    ones = torch.ones_like
    mis = estimate_Lo(n, wo, material, FURNACE_ENV, ones, N, torch.Generator().manual_seed(7)).diffuse
    mean, se = per_point_mean_and_se(mis[:, 0])
    assert se > 0.0 and abs(mean - 1.0) < 4.0 * se, f"MIS furnace {mean:.5f} +- {se:.1e}"
    torch.testing.assert_close(mis[:, 0], mis[:, 2], rtol=1e-12, atol=0.0)
    ref = estimate_Lo_reference(n, wo, material, ones, 3 * N, torch.Generator().manual_seed(8)).diffuse
    torch.testing.assert_close(ref, torch.ones_like(ref), rtol=0.0, atol=1e-9)


SPEC_ROUGHNESS = (0.089, 0.15, 0.25, 0.4, 0.6, 0.8, 1.0)
SPEC_VIEW_DEG = (0.0, 30.0, 60.0, 80.0, 89.0)


def specular_albedo(roughness: float, view_deg: float, f0: float, brdf: BRDFModel = BRDFModel()) -> float:
    """``int f_spec(wo, wi) cos dwi`` over the hemisphere, in a frame centred on the mirror direction."""
    m = Material(torch.ones(3, dtype=DTYPE), tensor(roughness)[0], brdf)
    wo = local_view(view_deg)
    mirror = tensor(-float(wo[0]), -float(wo[1]), float(wo[2]))
    def integrand(w):
        return brdf_eval(m, UP, wo, w, f0).specular[..., 0] * w[..., 2]
    return integrate_upper_hemisphere(integrand, mirror, eps=1e-3 * roughness**4, phi_panels=48, ds_max=0.5,
                                      dt_max=0.05)


@pytest.mark.parametrize("shadowing", ("smith", "schlick"))
@pytest.mark.parametrize("view_deg", SPEC_VIEW_DEG)
@pytest.mark.parametrize("roughness", SPEC_ROUGHNESS)
def test_specular_lobe_reflects_no_more_than_it_receives(roughness: float, view_deg: float, shadowing: str) -> None:
    """White furnace of the GGX lobe alone: directional albedo <= 1 with F = 1 (f0 = 1); with f0 = 0.04 below that,
    and well below 1 unless the view grazes (where Fresnel itself reaches 0.4 at 80 degrees)."""
    brdf = BRDFModel(shadowing=shadowing)
    white = specular_albedo(roughness, view_deg, 1.0, brdf)
    dielectric = specular_albedo(roughness, view_deg, F0_DIELECTRIC, brdf)
    assert 0.0 < white <= 1.0 + 1e-6, f"specular albedo {white:.6f} with F = 1"
    assert dielectric <= white, f"specular albedo {dielectric:.6f} with f0 = 0.04, {white:.6f} with F = 1"
    assert view_deg > 60.0 or dielectric < 0.2, f"specular albedo {dielectric:.6f} with f0 = 0.04"


def test_exact_shadowing_loses_less_energy_than_schlick_k() -> None:
    """The official ``k = (r+1)^2/8`` shadows more than the exact Smith term between the extremes (at r = 1 the
    two G1 coincide, ``2c / (c + 1)``): white-furnace albedos at r = 0.5, 60 degrees, 0.86 exact and 0.59."""
    exact = specular_albedo(0.5, 60.0, 1.0, BRDFModel(shadowing="smith"))
    schlick = specular_albedo(0.5, 60.0, 1.0, BRDFModel(shadowing="schlick"))
    assert schlick < 0.75 * exact, f"exact {exact:.4f}, schlick-k {schlick:.4f}"
    assert specular_albedo(1.0, 60.0, 1.0, BRDFModel(shadowing="smith")) == pytest.approx(
        specular_albedo(1.0, 60.0, 1.0, BRDFModel(shadowing="schlick")), rel=1e-12)


def test_specular_albedo_near_one_for_smooth_surfaces_at_normal_incidence() -> None:
    """As alpha -> 0 at normal incidence, G -> 1 and the lobe returns (almost) everything: the quadrature sees it."""
    assert specular_albedo(0.089, 0.0, 1.0) == pytest.approx(1.0, abs=1e-3)
    assert specular_albedo(0.089, 0.0, F0_DIELECTRIC) == pytest.approx(F0_DIELECTRIC, rel=2e-3)


# --------------------------------------------------------------------------- support, reciprocity


@pytest.mark.parametrize("brdf", MODELS)
def test_brdf_is_zero_below_the_surface(brdf: BRDFModel) -> None:
    gen = torch.Generator().manual_seed(4)
    up, other = random_upper(64, gen), random_upper(64, gen)
    down = other * tensor(1.0, 1.0, -1.0)
    m = Material(torch.rand(64, 3, generator=gen, dtype=DTYPE),
                 0.089 + 0.911 * torch.rand(64, generator=gen, dtype=DTYPE), brdf)
    for wo, wi in ((up, down), (down, up), (down, down * tensor(-1.0, 1.0, 1.0))):
        f = brdf_eval(m, UP, wo, wi)
        assert not bool(f.diffuse.any()) and not bool(f.specular.any())
    f = brdf_eval(m, UP, up, other)
    assert bool((f.diffuse > 0).all()) and bool((f.specular > 0).all())


@pytest.mark.parametrize("brdf", MODELS)
def test_brdf_is_reciprocal(brdf: BRDFModel) -> None:
    gen = torch.Generator().manual_seed(5)
    n = unit(0.2, 0.4, 0.9)
    frame = orthonormal_frame(n)
    def world(v):
        return v[..., :1] * frame[1] + v[..., 1:2] * frame[2] + v[..., 2:] * frame[0]
    wo, wi = world(random_upper(256, gen)), world(random_upper(256, gen))
    m = Material(torch.rand(256, 3, generator=gen, dtype=DTYPE),
                 0.089 + 0.911 * torch.rand(256, generator=gen, dtype=DTYPE), brdf)
    a, b = brdf_eval(m, n, wo, wi), brdf_eval(m, n, wi, wo)
    torch.testing.assert_close(a.diffuse, b.diffuse, rtol=1e-13, atol=0.0)
    torch.testing.assert_close(a.specular, b.specular, rtol=1e-12, atol=0.0)


def test_brdf_matches_the_formula_of_the_design_doc() -> None:
    """``albedo / pi + F D G / (4 nl nv)`` written out by hand at one configuration."""
    n, wo, wi = UP, unit(0.3, 0.1, 0.8), unit(-0.5, 0.2, 0.6)
    r, albedo = 0.35, tensor(0.2, 0.5, 0.9)
    h = (wo + wi) / (wo + wi).norm()
    a2 = r**4
    D = a2 / (math.pi * (float(h[2]) ** 2 * (a2 - 1) + 1) ** 2)
    F = 0.04 + 0.96 * (1 - float(wo @ h)) ** 5
    k = (r + 1) ** 2 / 8
    nl, nv = float(wi[2]), float(wo[2])
    G = nl / (nl * (1 - k) + k) * nv / (nv * (1 - k) + k)
    f = brdf_eval(Material(albedo, tensor(r)[0], OFFICIAL_BRDF), n, wo, wi)
    torch.testing.assert_close(f.diffuse, albedo / math.pi, rtol=1e-14, atol=0.0)
    torch.testing.assert_close(f.specular, torch.full((3,), F * D * G / (4 * nl * nv), dtype=DTYPE),
                               rtol=1e-12, atol=0.0)
    torch.testing.assert_close(f.total, f.diffuse + f.specular)
    # the default model: Burley's diffuse and the exact Smith G1 = 2c / (c + sqrt(a^2 + (1 - a^2) c^2))
    a2 = r**4
    G = math.prod(2 * c / (c + math.sqrt(a2 + (1 - a2) * c * c)) for c in (nl, nv))
    fd90 = 0.5 + 2 * r * float(wi @ h) ** 2
    burley = (1 + (fd90 - 1) * (1 - nl) ** 5) * (1 + (fd90 - 1) * (1 - nv) ** 5)
    f = brdf_eval(Material(albedo, tensor(r)[0]), n, wo, wi)
    torch.testing.assert_close(f.diffuse, albedo / math.pi * burley, rtol=1e-13, atol=0.0)
    torch.testing.assert_close(f.specular, torch.full((3,), F * D * G / (4 * nl * nv), dtype=DTYPE),
                               rtol=1e-12, atol=0.0)


# --------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("brdf", MODELS)
def test_brdf_gradcheck(brdf: BRDFModel) -> None:
    """float64 gradients w.r.t. albedo, roughness, n, wo and wi, at directions away from the kinks."""
    gen = torch.Generator().manual_seed(6)
    B = 4
    albedo = torch.rand(B, 3, generator=gen, dtype=DTYPE).requires_grad_()
    rough = (0.1 + 0.8 * torch.rand(B, generator=gen, dtype=DTYPE)).requires_grad_()
    n = UP.expand(B, 3).clone().requires_grad_()
    wo = random_upper(B, gen, min_cos=0.2).requires_grad_()
    wi = random_upper(B, gen, min_cos=0.2).requires_grad_()
    def f(albedo, rough, n, wo, wi):
        v = brdf_eval(Material(albedo, rough, brdf), n, wo, wi)
        return v.diffuse, v.specular
    assert torch.autograd.gradcheck(f, (albedo, rough, n, wo, wi), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_sg_eval_gradcheck() -> None:
    gen = torch.Generator().manual_seed(7)
    axis = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen, dtype=DTYPE), dim=-1).requires_grad_()
    sharpness = tensor(0.5, 5.0, 30.0).requires_grad_()
    amplitude = torch.rand(3, 3, generator=gen, dtype=DTYPE).requires_grad_()
    w = torch.nn.functional.normalize(torch.randn(5, 3, generator=gen, dtype=DTYPE), dim=-1)
    def f(axis, sharpness, amplitude):
        return sg_eval(w, SGMixture(axis, sharpness, amplitude))
    assert torch.autograd.gradcheck(f, (axis, sharpness, amplitude), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_sg_eval_with_given_lobes_keeps_every_gradient() -> None:
    """Lobe values handed in detached (the light pdf's) change neither the value nor any gradient, on the
    hand-written backward's path and on autograd's (``w`` differentiable: the given lobes are not used). (Not a
    gradcheck: with the lobes fixed, finite differences in the axes cannot move the value.)"""
    gen = torch.Generator().manual_seed(11)
    axis = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=DTYPE), dim=-1).requires_grad_()
    sharpness = tensor(0.5, 5.0, 30.0, 300.0).requires_grad_()
    amplitude = torch.rand(4, 3, generator=gen, dtype=DTYPE).requires_grad_()
    w = torch.nn.functional.normalize(torch.randn(6, 2, 3, generator=gen, dtype=DTYPE), dim=-1)
    sg = lambda: SGMixture(axis, sharpness, amplitude)
    lobes = sg_lobes(w, sg()).detach()

    cot = torch.randn(6, 2, 3, generator=gen, dtype=DTYPE)
    for wd in (w, w.clone().requires_grad_()):
        ref_val, got_val = sg_eval(wd, sg()), sg_eval(wd, sg(), lobes)
        torch.testing.assert_close(got_val, ref_val, rtol=1e-12, atol=1e-14)
        ref = torch.autograd.grad((ref_val * cot).sum(), (axis, sharpness, amplitude))
        got = torch.autograd.grad((got_val * cot).sum(), (axis, sharpness, amplitude))
        for a, b in zip(ref, got):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
