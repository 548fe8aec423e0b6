"""Every direction sampler against its own pdf, by the chi-square test of tests/chi2.py.

Each sampler is a pure warp of uniform numbers drawn from a seeded ``torch.Generator``
(float64, 1e6 directions per test). Bins are centred on where each distribution lives (the
normal for cosine, the mirror direction of ``wo`` for GGX, the lobe axis for an SG lobe, the
normal or the sharpest lobe for an SG mixture) and cover the whole sphere, directions below
the horizon included.

Significance: this module runs ``TEST_COUNT`` statistical tests that must pass; each must reach
the Sidak-corrected level ``LEVEL = 1 - (1 - 0.01)^(1 / TEST_COUNT)`` (1.3e-4 for the 75 here), so that the
whole module fails by chance with probability 0.01, as Mitsuba 3's ``ChiSquareTest`` does with
``test_count``. The tests of the harness's power must instead reach ``p < 1e-6``.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.stats
import torch

from chi2 import LEVEL_FOR_POWER, SphericalBinning, chi2_test, draw_uniform, pooled_chi2, sidak_level
from quadrature import DTYPE, centred_direction, integrate_upper_hemisphere
from nefii.render.brdf import G1_smith_ggx
from nefii.render.samplers import (pdf_cosine, pdf_ggx_vndf, pdf_sg_mixture, pick_lobe, sample_cosine,
                                   sample_ggx_vndf, sample_sg_lobe, sample_sg_mixture, sg_selection_probs)
from nefii.render.sg import SGMixture

NUM_SAMPLES = 1_000_000

COSINE_SEEDS = (101, 102, 103)
GGX_ROUGHNESS = (0.089, 0.3, 0.6, 1.0)
GGX_VIEW_DEG = (0.0, 45.0, 85.0)
GGX_SEEDS = (201, 202)
NEARLY_NORMAL_ROUGHNESS = (0.089, 0.6)
SG_SHARPNESS = (1.0, 10.0, 100.0, 1000.0)
SG_SEEDS = (301, 302, 303)
MIXTURE_SEEDS = (401, 402, 403)
SHARP_MIXTURE_CENTRES = (0, 1)          # bins centred on the lambda = 1000 lobe, then on the lambda = 300 lobe
SHARP_MIXTURE_SEEDS = (501, 502)
PICK_SEEDS = (601, 602, 603)

TEST_COUNT = (len(COSINE_SEEDS)
              + 2 * len(GGX_ROUGHNESS) * len(GGX_VIEW_DEG) * len(GGX_SEEDS)   # chi-square + horizon fraction
              + len(NEARLY_NORMAL_ROUGHNESS)
              + len(SG_SHARPNESS) * len(SG_SEEDS)
              + len(MIXTURE_SEEDS)
              + len(SHARP_MIXTURE_CENTRES) * len(SHARP_MIXTURE_SEEDS)
              + len(PICK_SEEDS))
LEVEL = sidak_level(0.01, TEST_COUNT)


def tensor(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=DTYPE)


def unit(*values: float) -> torch.Tensor:
    v = tensor(*values)
    return v / v.norm()


def assert_passes(result) -> None:
    assert result.failure is None and result.p_value > LEVEL, result.describe()


# --------------------------------------------------------------------------- the harness itself


def test_bins_cover_the_sphere_and_quadrature_gives_their_solid_angles() -> None:
    """With pdf = 1 the quadrature of each bin is its solid angle ``(t_hi - t_lo) 2 pi / n_phi``; they sum to 4 pi."""
    binning = SphericalBinning(tuple(unit(0.3, -0.2, 0.9).tolist()), kappa=300.0, n_theta=16, n_phi=8)
    areas = binning.integrate(lambda w: torch.ones(w.shape[:-1], dtype=DTYPE))
    edges = binning.t_edges()
    exact = (edges[1:] - edges[:-1]).unsqueeze(-1) * (2.0 * math.pi / binning.n_phi)
    torch.testing.assert_close(areas, exact.expand_as(areas), rtol=1e-10, atol=0.0)
    assert float(areas.sum()) == pytest.approx(4.0 * math.pi, rel=1e-12)
    # a direction in the middle of bin (i, j), built from the edges the quadrature used, is binned there
    t_mid = 0.5 * (edges[1:] + edges[:-1])
    phi_mid = (torch.arange(binning.n_phi, dtype=DTYPE) + 0.5) * (2.0 * math.pi / binning.n_phi)
    w = centred_direction(binning.frame, t_mid.unsqueeze(-1), phi_mid)
    assert torch.equal(binning.bin_of(w.reshape(-1, 3)), torch.arange(binning.n_theta * binning.n_phi))


def test_pooling_keeps_every_sample_and_fails_samples_where_the_pdf_is_zero() -> None:
    observed = np.array([0, 1, 2, 3, 50, 4, 0, 10])
    expected = np.array([0.0, 1.5, 2.0, 2.5, 48.0, 4.0, 0.5, 9.5])
    stat, dof, failure = pooled_chi2(observed, expected)
    # cells below 5 pool by increasing expectation: {0.5, 1.5, 2.0, 2.5} -> 6.5, {4.0} alone stays under 5 and is last
    want = (6 - 6.5) ** 2 / 6.5 + (10 - 9.5) ** 2 / 9.5 + (50 - 48.0) ** 2 / 48.0 + (4 - 4.0) ** 2 / 4.0
    assert failure is None and dof == 3 and stat == pytest.approx(want)
    _, _, failure = pooled_chi2(np.array([1, 5]), np.array([0.0, 6.0]))
    assert failure is not None


# --------------------------------------------------------------------------- cosine

COSINE_BINNING = SphericalBinning((0.0, 0.0, 1.0), kappa=0.0)


@functools.lru_cache(maxsize=None)
def cosine_integral() -> torch.Tensor:
    return COSINE_BINNING.integrate(pdf_cosine)


@pytest.mark.parametrize("seed", COSINE_SEEDS)
def test_cosine_chi2(seed: int) -> None:
    assert_passes(chi2_test(sample_cosine, None, COSINE_BINNING, seed=seed, integral=cosine_integral()))


# --------------------------------------------------------------------------- GGX visible normals


def ggx_view(view_deg: float) -> torch.Tensor:
    """Local ``wo`` at ``view_deg`` from the normal, at an azimuth on no axis."""
    theta, phi = math.radians(view_deg), 0.9
    return tensor(math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))


@functools.lru_cache(maxsize=None)
def ggx_case(roughness: float, view_deg: float) -> tuple[torch.Tensor, torch.Tensor, SphericalBinning, torch.Tensor]:
    """``(wo, alpha, binning, integral)``: bins about the mirror direction, kappa ~ 1 / (4 alpha^2)."""
    wo, alpha = ggx_view(view_deg), tensor(roughness**2)[0]
    mirror = (-float(wo[0]), -float(wo[1]), float(wo[2]))
    binning = SphericalBinning(mirror, kappa=min(1.0 / (4.0 * float(alpha) ** 2), 5000.0))
    return wo, alpha, binning, binning.integrate(lambda w: pdf_ggx_vndf(wo, w, alpha))


@pytest.mark.parametrize("seed", GGX_SEEDS)
@pytest.mark.parametrize("view_deg", GGX_VIEW_DEG)
@pytest.mark.parametrize("roughness", GGX_ROUGHNESS)
def test_ggx_vndf_chi2_and_horizon_fraction(roughness: float, view_deg: float, seed: int) -> None:
    """The whole-sphere chi-square, and the share of samples above the surface against the pdf's mass there."""
    wo, alpha, binning, integral = ggx_case(roughness, view_deg)
    samples = sample_ggx_vndf(wo, alpha, draw_uniform(NUM_SAMPLES, 2, seed))
    assert_passes(chi2_test(None, None, binning, samples=samples, integral=integral))

    mass_above = integrate_upper_hemisphere(lambda w: pdf_ggx_vndf(wo, w, alpha), binning.centre)
    share_above = float((samples[:, 2] > 0).double().mean())
    se = math.sqrt(max(mass_above * (1.0 - mass_above), 1e-12) / NUM_SAMPLES)
    p = 2.0 * scipy.stats.norm.sf(abs(share_above - mass_above) / se)
    assert p > LEVEL, f"share above the surface {share_above:.6f}, pdf mass above {mass_above:.6f} (se {se:.1e})"


@pytest.mark.parametrize("roughness", NEARLY_NORMAL_ROUGHNESS)
def test_ggx_vndf_chi2_at_nearly_normal_view(roughness: float) -> None:
    """``wo`` off the normal by ~3e-17, as ``Frame.from_normal(n).to_local(n)`` returns it in float64.

    Regression: the visible-normal tangent ``T1`` was left unnormalised for ``0 < |vh.xy|^2 < 1e-30``
    (the clamp of its inverse length), which collapsed the sampled normals onto the normal and
    biased the MIS estimator by 4% at normal incidence.
    """
    wo, alpha, binning, integral = ggx_case(roughness, 0.0)
    nearly = tensor(0.0, -2.7755575615628914e-17, 1.0)
    assert_passes(chi2_test(lambda u: sample_ggx_vndf(nearly, alpha, u), None, binning, seed=GGX_SEEDS[0],
                            integral=integral))


# --------------------------------------------------------------------------- one SG lobe

SG_AXIS = unit(0.36, -0.48, 0.8)


def sg_lobe_pdf(axis: torch.Tensor, sharpness: float):
    """The normalised lobe ``lambda / (2 pi (1 - e^{-2 lambda})) e^{lambda (w.xi - 1)}``, written here independently."""
    norm = sharpness / (2.0 * math.pi * -math.expm1(-2.0 * sharpness))
    return lambda w: norm * torch.exp(sharpness * (w @ axis - 1.0))


@functools.lru_cache(maxsize=None)
def sg_lobe_case(sharpness: float) -> tuple[SphericalBinning, torch.Tensor]:
    binning = SphericalBinning(tuple(SG_AXIS.tolist()), kappa=sharpness / 2.0)
    return binning, binning.integrate(sg_lobe_pdf(SG_AXIS, sharpness))


@pytest.mark.parametrize("seed", SG_SEEDS)
@pytest.mark.parametrize("sharpness", SG_SHARPNESS)
def test_sg_lobe_chi2(sharpness: float, seed: int) -> None:
    binning, integral = sg_lobe_case(sharpness)
    lam = tensor(sharpness)[0]
    assert_passes(chi2_test(lambda u: sample_sg_lobe(SG_AXIS, lam, u), None, binning, seed=seed, integral=integral))


# --------------------------------------------------------------------------- SG mixture

MIXTURE_NORMAL = unit(0.2, -0.3, 0.93)


def mixture_env() -> SGMixture:
    """Seven lobes of sharpness 1 to 200, amplitudes 0.5 to 30; lobes 4 and 5 lie below the normal's hemisphere."""
    axes = torch.stack([unit(0.0, 0.0, 1.0), unit(0.6, 0.0, 0.8), unit(-0.5, 0.5, 0.707), unit(0.0, -0.8, 0.6),
                        unit(0.7, 0.7, -0.14), unit(-0.3, -0.3, -0.9), unit(0.1, 0.9, 0.42)])
    sharpness = tensor(1.0, 200.0, 50.0, 10.0, 100.0, 20.0, 150.0)
    amplitude = torch.stack([tensor(0.5, 0.6, 0.7), tensor(30.0, 28.0, 25.0), tensor(2.0, 1.0, 0.5),
                             tensor(1.0, 2.0, 3.0), tensor(5.0, 5.0, 5.0), tensor(3.0, 3.0, 3.0),
                             tensor(0.2, 4.0, 1.0)])
    return SGMixture(axes, sharpness, amplitude)


def sharp_mixture_env() -> SGMixture:
    """Six lobes of sharpness 1 to 1000 (lobe 0: 1000, lobe 1: 300); lobe 4 lies below the normal's hemisphere."""
    axes = torch.stack([unit(0.3, 0.2, 0.93), unit(-0.6, 0.1, 0.79), unit(0.0, 0.0, 1.0), unit(0.2, -0.9, 0.4),
                        unit(0.5, 0.5, -0.7), unit(-0.2, 0.7, 0.68)])
    sharpness = tensor(1000.0, 300.0, 1.0, 30.0, 100.0, 5.0)
    amplitude = torch.stack([tensor(500.0, 480.0, 450.0), tensor(40.0, 40.0, 40.0), tensor(0.3, 0.4, 0.6),
                             tensor(2.0, 2.0, 2.0), tensor(20.0, 10.0, 5.0), tensor(1.0, 0.5, 0.2)])
    return SGMixture(axes, sharpness, amplitude)


def test_mixture_fixtures_have_lobes_below_the_normal() -> None:
    for env in (mixture_env(), sharp_mixture_env()):
        cos = env.axis @ MIXTURE_NORMAL
        assert bool((cos < 0).any()) and bool((cos > 0).any())
        probs = sg_selection_probs(env, MIXTURE_NORMAL)
        assert bool((probs > 0).all()), "the eps floor of Eq. 6 keeps lobes below the surface selectable"


@functools.lru_cache(maxsize=None)
def mixture_case() -> tuple[SGMixture, torch.Tensor, SphericalBinning, torch.Tensor]:
    env = mixture_env()
    probs = sg_selection_probs(env, MIXTURE_NORMAL)
    binning = SphericalBinning(tuple(MIXTURE_NORMAL.tolist()), kappa=1.0, n_theta=64, n_phi=64)
    return env, probs, binning, binning.integrate(lambda w: pdf_sg_mixture(env, probs, w))


@functools.lru_cache(maxsize=None)
def sharp_mixture_case(centre_lobe: int) -> tuple[SGMixture, torch.Tensor, SphericalBinning, torch.Tensor]:
    env = sharp_mixture_env()
    probs = sg_selection_probs(env, MIXTURE_NORMAL)
    binning = SphericalBinning(tuple(env.axis[centre_lobe].tolist()), kappa=float(env.sharpness[centre_lobe]) / 2.0)
    return env, probs, binning, binning.integrate(lambda w: pdf_sg_mixture(env, probs, w))


@pytest.mark.parametrize("seed", MIXTURE_SEEDS)
def test_sg_mixture_chi2(seed: int) -> None:
    """The mixture as a density over directions, in bins about the normal with a moderate zoom."""
    env, probs, binning, integral = mixture_case()
    assert_passes(chi2_test(lambda u: sample_sg_mixture(env, probs, u), None, binning, dim_u=3, seed=seed,
                            integral=integral))


@pytest.mark.parametrize("seed", SHARP_MIXTURE_SEEDS)
@pytest.mark.parametrize("centre_lobe", SHARP_MIXTURE_CENTRES)
def test_sharp_sg_mixture_chi2(centre_lobe: int, seed: int) -> None:
    """A mixture with lobes up to lambda = 1000, in bins zoomed on one sharp lobe (the rest lands in outer bins)."""
    env, probs, binning, integral = sharp_mixture_case(centre_lobe)
    assert_passes(chi2_test(lambda u: sample_sg_mixture(env, probs, u), None, binning, dim_u=3, seed=seed,
                            integral=integral))


@pytest.mark.parametrize("seed", PICK_SEEDS)
def test_pick_lobe_frequencies_match_probs(seed: int) -> None:
    """Lobe choice against ``probs`` for two shading points at once (as the estimator batches it).

    Lobes 0, 3 and 7 have no energy (amplitude 0), so probability 0: they must never be picked.
    """
    env = sharp_mixture_env()
    amplitude = torch.cat([torch.zeros(1, 3, dtype=DTYPE), env.amplitude[:2], torch.zeros(1, 3, dtype=DTYPE),
                           env.amplitude[2:], torch.zeros(1, 3, dtype=DTYPE)])
    axis = torch.cat([env.axis[:1], env.axis[:2], env.axis[:1], env.axis[2:], env.axis[:1]])
    sharpness = torch.cat([env.sharpness[:1], env.sharpness[:2], env.sharpness[:1], env.sharpness[2:],
                           env.sharpness[:1]])
    padded = SGMixture(axis, sharpness, amplitude)
    normals = torch.stack([MIXTURE_NORMAL, unit(-0.5, 0.2, -0.8)])
    probs = sg_selection_probs(padded, normals).unsqueeze(-2)                  # (2, 1, K)
    zero = [0, 3, padded.num_lobes - 1]
    assert bool((probs[..., zero] == 0).all())
    u = draw_uniform(NUM_SAMPLES, 2, seed).T.contiguous()                      # (2, N)
    k = pick_lobe(probs, u)
    assert k.shape == u.shape
    stat, dof = 0.0, 0
    for row in range(2):
        counts = torch.bincount(k[row], minlength=padded.num_lobes).double()
        assert int(counts[zero].sum()) == 0, f"lobes of probability 0 were picked: {counts[zero].tolist()}"
        s, d, failure = pooled_chi2(counts.numpy(), NUM_SAMPLES * probs[row, 0].numpy())
        assert failure is None
        stat, dof = stat + s, dof + d
    p = float(scipy.stats.chi2.sf(stat, dof))
    assert p > LEVEL, f"chi2 = {stat:.1f} on {dof} dof, p = {p:.3g}"


# --------------------------------------------------------------------------- every pdf integrates to 1


def all_integrals():
    yield "cosine", cosine_integral
    for r in GGX_ROUGHNESS:
        for v in GGX_VIEW_DEG:
            yield f"ggx-r{r}-view{v:g}", functools.partial(lambda r, v: ggx_case(r, v)[3], r, v)
    for lam in SG_SHARPNESS:
        yield f"sg-lobe-{lam:g}", functools.partial(lambda lam: sg_lobe_case(lam)[1], lam)
    yield "mixture", lambda: mixture_case()[3]
    for c in SHARP_MIXTURE_CENTRES:
        yield f"sharp-mixture-{c}", functools.partial(lambda c: sharp_mixture_case(c)[3], c)


INTEGRALS = dict(all_integrals())


@pytest.mark.parametrize("name", list(INTEGRALS))
def test_pdf_integrates_to_one(name: str) -> None:
    """The quadrature of the pdf over all bins (the whole sphere) is 1."""
    total = float(INTEGRALS[name]().sum())
    assert total == pytest.approx(1.0, abs=1e-4)


# --------------------------------------------------------------------------- the harness has power


def test_power_cosine_pdf_scaled_on_one_half() -> None:
    """Cosine pdf times 1.05 where x > 0 and 0.95 where x < 0: still normalised, wrong in shape."""
    def wrong(w):
        return pdf_cosine(w) * (1.0 + 0.05 * torch.sign(w[..., 0]))
    result = chi2_test(sample_cosine, wrong, COSINE_BINNING, seed=COSINE_SEEDS[0])
    assert result.pdf_integral == pytest.approx(1.0, abs=1e-4)
    assert result.p_value < LEVEL_FOR_POWER, result.describe()


def test_power_ggx_pdf_without_G1() -> None:
    wo, alpha, binning, _ = ggx_case(0.6, 45.0)
    def wrong(w):
        return pdf_ggx_vndf(wo, w, alpha) / G1_smith_ggx(wo[2], alpha)
    result = chi2_test(lambda u: sample_ggx_vndf(wo, alpha, u), wrong, binning, seed=GGX_SEEDS[0])
    assert result.p_value < LEVEL_FOR_POWER, result.describe()


@pytest.mark.parametrize("roughness", (0.089, 0.6))
def test_power_ggx_pdf_with_alpha_off_by_5_percent(roughness: float) -> None:
    """A normalised pdf of the wrong width (alpha * 1.05)."""
    wo, alpha, binning, _ = ggx_case(roughness, 45.0)
    result = chi2_test(lambda u: sample_ggx_vndf(wo, alpha, u), lambda w: pdf_ggx_vndf(wo, w, alpha * 1.05),
                       binning, seed=GGX_SEEDS[0])
    assert result.pdf_integral == pytest.approx(1.0, abs=1e-4)
    assert result.p_value < LEVEL_FOR_POWER, result.describe()


def test_power_sharp_sg_lobe_with_sharpness_off_by_5_percent() -> None:
    binning, _ = sg_lobe_case(1000.0)
    lam = tensor(1000.0)[0]
    result = chi2_test(lambda u: sample_sg_lobe(SG_AXIS, lam, u), sg_lobe_pdf(SG_AXIS, 1050.0), binning,
                       seed=SG_SEEDS[0])
    assert result.p_value < LEVEL_FOR_POWER, result.describe()


def test_power_mixture_sampled_by_amplitude_alone() -> None:
    """Lobes picked by ``mean|mu| max(n.xi, eps)`` (the official code's weights, without the lobe integral of
    Eq. 6) against the pdf of the weights with it: a mixture of the right lobes in the wrong proportions."""
    env, probs, binning, integral = mixture_case()
    weights = env.amplitude.abs().mean(-1) * (env.axis @ MIXTURE_NORMAL).clamp_min(0.01)
    result = chi2_test(lambda u: sample_sg_mixture(env, weights / weights.sum(), u), None, binning, dim_u=3,
                       seed=MIXTURE_SEEDS[0], integral=integral)
    assert result.p_value < LEVEL_FOR_POWER, result.describe()
