"""The MIS estimator of Eq. 2 (nefii.render.estimator) against its cosine-only sibling and a quadrature.

Every statistical comparison uses many independent shading points that share ``n``, ``wo`` and
the material, so each point's estimate is one independent draw of the same estimator: their
mean and standard error are then well defined. Incoming radiance is the SG environment itself
(no visibility). The quadrature is float64, graded about the mirror direction (tests/quadrature.py).
"""
from __future__ import annotations

import functools
import math

import pytest
import torch

from quadrature import DTYPE, integrate_sphere, orthonormal_frame
from nefii.render.brdf import Material, brdf_eval
from nefii.render.estimator import MIN_COS_VIEW, combine, estimate_Lo, sample_mis_directions, view_above_surface
from nefii.render.frame import Frame, reflect
from nefii.render.estimator_reference import estimate_Lo_reference
from nefii.render.mis import power_heuristic, power_heuristic_over_pdf
from nefii.render.samplers import pick_lobe
from nefii.render.sg import SGMixture, sg_eval, sg_lobes

NUM_POINTS = 20_000
NUM_SAMPLES = 4                 # MIS: 3 directions each; the reference gets 3 * NUM_SAMPLES directions
Z_MAX = 4.0


def unit(*values: float) -> torch.Tensor:
    v = torch.tensor(values, dtype=DTYPE)
    return v / v.norm()


def environment(dtype: torch.dtype = DTYPE) -> SGMixture:
    """A wide sky, a sun (lambda 30), a warm lobe, and a lobe below the surface."""
    axes = torch.stack([unit(0.0, 0.0, 1.0), unit(0.5, 0.3, 0.8), unit(-0.6, 0.2, 0.5), unit(0.2, -0.5, -0.8)])
    sharpness = torch.tensor([1.0, 30.0, 8.0, 5.0], dtype=DTYPE)
    amplitude = torch.tensor([[0.6, 0.7, 0.9], [12.0, 11.0, 9.0], [2.0, 1.5, 1.0], [1.0, 1.0, 1.0]], dtype=DTYPE)
    return SGMixture(axes.to(dtype), sharpness.to(dtype), amplitude.to(dtype))


NORMAL = unit(0.1, -0.2, 0.97)
ALBEDO = torch.tensor([0.6, 0.4, 0.2], dtype=DTYPE)


def view(view_deg: float) -> torch.Tensor:
    n, e1, e2 = orthonormal_frame(NORMAL)
    theta = math.radians(view_deg)
    return math.cos(theta) * n + math.sin(theta) * (0.6 * e1 + 0.8 * e2)


@functools.lru_cache(maxsize=None)
def quadrature_Lo(roughness: float, view_deg: float) -> torch.Tensor:
    """``(6,)``: diffuse RGB then specular RGB of ``int f_r L_i (wi.n) dwi``, graded about the mirror direction."""
    env, wo = environment(), view(view_deg)
    material = Material(ALBEDO, torch.tensor(roughness, dtype=DTYPE))
    mirror = 2.0 * (wo @ NORMAL) * NORMAL - wo
    def integrand(w):
        f = brdf_eval(material, NORMAL, wo, w)
        radiance = sg_eval(w, env) * (w @ NORMAL).clamp_min(0.0).unsqueeze(-1)
        return torch.cat([f.diffuse * radiance, f.specular * radiance], -1)
    return integrate_sphere(integrand, mirror, eps=1e-3 * roughness**4)


def per_point_estimates(roughness: float, view_deg: float, reference: bool, seed: int) -> torch.Tensor:
    """``(NUM_POINTS, 6)`` independent estimates (diffuse RGB, specular RGB) at one shading configuration."""
    env, B = environment(), NUM_POINTS
    n, wo = NORMAL.expand(B, 3), view(view_deg).expand(B, 3)
    material = Material(ALBEDO.expand(B, 3), torch.full((B,), roughness, dtype=DTYPE))
    gen = torch.Generator().manual_seed(seed)
    def incoming(wi):
        return sg_eval(wi, env)
    if reference:
        est = estimate_Lo_reference(n, wo, material, incoming, 3 * NUM_SAMPLES, gen)
    else:
        est = estimate_Lo(n, wo, material, env, incoming, NUM_SAMPLES, gen)
    return torch.cat([est.diffuse, est.specular], -1)


def mean_se(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return x.mean(0), x.std(0) / math.sqrt(x.shape[0])


CASES = [(r, v) for r in (0.8, 0.2) for v in (0.0, 50.0)]


@pytest.mark.parametrize("roughness, view_deg", CASES)
def test_mis_and_reference_agree_with_each_other_and_with_quadrature(roughness: float, view_deg: float) -> None:
    mis_mean, mis_se = mean_se(per_point_estimates(roughness, view_deg, reference=False, seed=10))
    ref_mean, ref_se = mean_se(per_point_estimates(roughness, view_deg, reference=True, seed=20))
    exact = quadrature_Lo(roughness, view_deg)
    assert bool((mis_se > 0).all()) and bool((ref_se > 0).all())
    z_mis_ref = (mis_mean - ref_mean) / (mis_se**2 + ref_se**2).sqrt()
    z_mis = (mis_mean - exact) / mis_se
    z_ref = (ref_mean - exact) / ref_se
    report = (f"quadrature {exact.tolist()}\nMIS {mis_mean.tolist()} +- {mis_se.tolist()}\n"
              f"reference {ref_mean.tolist()} +- {ref_se.tolist()}")
    assert float(z_mis_ref.abs().max()) < Z_MAX, report
    assert float(z_mis.abs().max()) < Z_MAX, report
    assert float(z_ref.abs().max()) < Z_MAX, report


@pytest.mark.parametrize("view_deg", (0.0, 50.0))
def test_mis_has_lower_variance_than_cosine_sampling_for_a_glossy_surface(view_deg: float) -> None:
    """At equal directions (3N each), for roughness 0.2: the specular lobe and the total RGB."""
    mis = per_point_estimates(0.2, view_deg, reference=False, seed=30)
    ref = per_point_estimates(0.2, view_deg, reference=True, seed=40)
    var_spec_mis, var_spec_ref = float(mis[:, 3:].sum(-1).var()), float(ref[:, 3:].sum(-1).var())
    var_mis, var_ref = float((mis[:, :3] + mis[:, 3:]).sum(-1).var()), float((ref[:, :3] + ref[:, 3:]).sum(-1).var())
    assert var_spec_mis < 0.5 * var_spec_ref, (var_spec_mis, var_spec_ref)
    assert var_mis < var_ref, (var_mis, var_ref)


# --------------------------------------------------------------------------- MIS weights


def test_power_heuristic_weights_sum_to_one() -> None:
    """Over strategies, for positive densities spanning 1e-150..1e150 (squares would over/underflow)."""
    gen = torch.Generator().manual_seed(1)
    p = 10.0 ** (300.0 * torch.rand(4096, 3, generator=gen, dtype=DTYPE) - 150.0)
    p = torch.cat([p, torch.tensor([[1e200, 1e200, 1.0], [1e-200, 3e-200, 0.0], [1.0, 1.0, 1.0]], dtype=DTYPE)])
    w = torch.stack([power_heuristic(p[:, s], p) for s in range(3)], -1)
    torch.testing.assert_close(w.sum(-1), torch.ones(p.shape[0], dtype=DTYPE), rtol=0.0, atol=1e-12)
    torch.testing.assert_close(w[-3], torch.tensor([0.5, 0.5, 0.0], dtype=DTYPE))
    torch.testing.assert_close(w[-2], torch.tensor([0.1, 0.9, 0.0], dtype=DTYPE))
    torch.testing.assert_close(w[-1], torch.full((3,), 1.0 / 3.0, dtype=DTYPE))
    p32 = p[:-3].float().clamp(1e-30, 1e30)
    w32 = torch.stack([power_heuristic(p32[:, s], p32) for s in range(3)], -1)
    torch.testing.assert_close(w32.sum(-1), torch.ones(p32.shape[0]), rtol=0.0, atol=1e-5)


def test_power_heuristic_over_pdf_is_weight_over_density() -> None:
    gen = torch.Generator().manual_seed(2)
    # ratios of densities down to 1e-100, whose squares power_heuristic still represents
    p = 10.0 ** (100.0 * torch.rand(4096, 3, generator=gen, dtype=DTYPE) - 50.0)
    for s in range(3):
        torch.testing.assert_close(power_heuristic_over_pdf(p[:, s], p), power_heuristic(p[:, s], p) / p[:, s],
                                   rtol=1e-12, atol=0.0)
    # p_s / sum_j p_j^2 written out, where nothing overflows
    q = torch.tensor([[0.5, 2.0, 1.0]], dtype=DTYPE)
    assert float(power_heuristic_over_pdf(q[:, 0], q)) == pytest.approx(0.5 / 5.25, rel=1e-14)


@pytest.mark.parametrize("helper", (power_heuristic, power_heuristic_over_pdf))
def test_mis_weights_are_zero_not_nan_for_degenerate_densities(helper) -> None:
    inf = math.inf
    p = torch.tensor([[0.0, 0.0, 0.0], [inf, 1.0, 2.0], [inf, inf, 1.0], [0.0, 1.0, 2.0]], dtype=DTYPE)
    w = helper(p[:, 0], p)
    assert torch.equal(w, torch.zeros(4, dtype=DTYPE)), w
    w_other = helper(p[:, 1], p)
    assert bool(torch.isfinite(w_other).all())
    assert float(w_other[0]) == 0.0 and float(w_other[1]) == 0.0


# --------------------------------------------------------------------------- shading frames


def test_frames_are_right_handed_orthonormal_bases_for_every_normal() -> None:
    """Including the poles, the equator and the sign flip at n.z = 0 of the branchless basis."""
    gen = torch.Generator().manual_seed(12)
    special = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.8, 0.0],
                            [0.6, 0.8, -1e-300], [1e-9, 0.0, -1.0]], dtype=DTYPE)
    n = torch.cat([special, torch.randn(1000, 3, generator=gen, dtype=DTYPE)])
    n = n / n.norm(dim=-1, keepdim=True)
    f = Frame.from_normal(n)
    basis = torch.stack([f.t, f.b, f.n], -2)                                        # (B, 3, 3), rows t, b, n
    torch.testing.assert_close(basis @ basis.transpose(-1, -2), torch.eye(3, dtype=DTYPE).expand_as(basis),
                               rtol=0.0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.cross(f.t, f.b), n, rtol=0.0, atol=1e-12)
    v = torch.randn(n.shape[0], 3, generator=gen, dtype=DTYPE)
    torch.testing.assert_close(f.to_world(f.to_local(v)), v, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(f.to_local(n)[:, 2], torch.ones(n.shape[0], dtype=DTYPE))


def test_reflect_mirrors_about_the_normal() -> None:
    wo, h = unit(0.3, -0.4, 0.8), unit(0.1, 0.2, 0.9)
    wi = reflect(wo, h)
    assert float(wi.norm()) == pytest.approx(1.0, abs=1e-14)
    assert float(wi @ h) == pytest.approx(float(wo @ h), abs=1e-14)
    torch.testing.assert_close(torch.linalg.cross(wi + wo, h), torch.zeros(3, dtype=DTYPE), rtol=0.0, atol=1e-14)


def test_view_above_surface_moves_only_views_below_the_surface() -> None:
    n = NORMAL.expand(4, 3)
    wo = torch.stack([view(a) for a in (30.0, 89.999, 100.0, 180.0)])
    moved = view_above_surface(n, wo)
    torch.testing.assert_close(moved[:1], wo[:1])
    torch.testing.assert_close(moved.norm(dim=-1), torch.ones(4, dtype=DTYPE))
    assert bool(((moved * n).sum(-1) > 0.5 * MIN_COS_VIEW).all())


# --------------------------------------------------------------------------- robustness


@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
@pytest.mark.parametrize("roughness", (0.089, 0.5))
def test_estimate_is_finite_for_grazing_and_back_facing_views(roughness: float, dtype: torch.dtype) -> None:
    """Views at 89.99, 90, 95 and 180 degrees from the normal, smooth (0.089) and rough surfaces: no NaN, no inf."""
    env = environment(dtype)
    n0 = NORMAL.to(dtype)
    c, e1, _ = (v.to(dtype) for v in orthonormal_frame(NORMAL))
    views = torch.stack([math.cos(math.radians(a)) * c + math.sin(math.radians(a)) * e1
                         for a in (89.99, 90.0, 95.0, 180.0)])
    B = views.shape[0]
    albedo = ALBEDO.to(dtype).expand(B, 3).clone().requires_grad_()
    rough = torch.full((B,), roughness, dtype=dtype, requires_grad=True)
    amplitude = env.amplitude.clone().requires_grad_()
    lit = SGMixture(env.axis, env.sharpness, amplitude)
    est = estimate_Lo(n0.expand(B, 3), views, Material(albedo, rough), lit, lambda w: sg_eval(w, lit), 64,
                      torch.Generator().manual_seed(5))
    assert bool(torch.isfinite(est.rgb).all()) and bool((est.rgb >= 0).all()), est.rgb
    est.rgb.sum().backward()
    for g in (albedo.grad, rough.grad, amplitude.grad):
        assert g is not None and bool(torch.isfinite(g).all())


# --------------------------------------------------------------------------- gradients


def shading_batch(B: int = 64):
    n = NORMAL.expand(B, 3)
    wo = view(35.0).expand(B, 3)
    albedo = (ALBEDO.expand(B, 3) * (0.5 + torch.rand(B, 1, generator=torch.Generator().manual_seed(3),
                                                      dtype=DTYPE))).clone().requires_grad_()
    rough = torch.full((B,), 0.3, dtype=DTYPE, requires_grad=True)
    env = environment()
    amplitude = env.amplitude.clone().requires_grad_()
    return n, wo, albedo, rough, SGMixture(env.axis, env.sharpness, amplitude), amplitude


def test_gradient_w_r_t_albedo_is_the_diffuse_estimate_over_albedo() -> None:
    """The estimate is linear in albedo, so ``d(sum_c L_o,c) / d albedo_c = L_o,diffuse,c / albedo_c``."""
    n, wo, albedo, rough, lit, _ = shading_batch()
    est = estimate_Lo(n, wo, Material(albedo, rough), lit, lambda w: sg_eval(w, lit), 8,
                      torch.Generator().manual_seed(9))
    est.rgb.sum().backward()
    torch.testing.assert_close(albedo.grad, est.diffuse.detach() / albedo.detach(), rtol=1e-12, atol=0.0)
    assert bool((albedo.grad > 0).all())


def test_gradient_w_r_t_sg_amplitude_is_the_estimate_of_each_lobe() -> None:
    """``d(sum L_o,c) / d mu_kc`` is the estimate, on the same directions, of lobe k of unit amplitude in channel c."""
    n, wo, albedo, rough, lit, amplitude = shading_batch()
    material = Material(albedo, rough)
    est = estimate_Lo(n, wo, material, lit, lambda w: sg_eval(w, lit), 8, torch.Generator().manual_seed(9))
    est.rgb.sum().backward()
    samples = sample_mis_directions(n, wo, rough.detach(), lit, 8, torch.Generator().manual_seed(9))
    lobes = sg_lobes(samples.wi, lit).detach()                                           # (B, S, K)
    with torch.no_grad():
        want = torch.stack([combine(samples, material, n, lobes[..., k:k + 1].expand(*lobes.shape[:-1], 3)).rgb.sum(0)
                            for k in range(lit.num_lobes)])
    torch.testing.assert_close(amplitude.grad, want, rtol=1e-10, atol=0.0)
    assert bool((amplitude.grad > 0).all())


def test_directions_are_drawn_without_gradient() -> None:
    """Samples carry no graph, and the roughness gradient is the one of ``f_r`` on those fixed samples."""
    n, wo, albedo, rough, lit, amplitude = shading_batch()
    axis = lit.axis.clone().requires_grad_()
    sharp = lit.sharpness.clone().requires_grad_()
    lit = SGMixture(axis, sharp, amplitude)
    samples = sample_mis_directions(n, wo, rough, lit, 8, torch.Generator().manual_seed(4))
    assert not samples.wi.requires_grad and not samples.weight.requires_grad and not samples.wo.requires_grad

    est = estimate_Lo(n, wo, Material(albedo, rough), lit, lambda w: sg_eval(w, lit), 8,
                      torch.Generator().manual_seed(4))
    g_rough, g_sharp = torch.autograd.grad(est.rgb.sum(), (rough, sharp))
    fixed = combine(samples, Material(albedo, rough), n, sg_eval(samples.wi, lit))
    f_rough, f_sharp = torch.autograd.grad(fixed.rgb.sum(), (rough, sharp))
    torch.testing.assert_close(g_rough, f_rough, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(g_sharp, f_sharp, rtol=1e-12, atol=0.0)
    assert float(g_rough.abs().sum()) > 0.0


# --------------------------------------------------------------------------- two independent half estimates


def test_the_mean_of_the_pair_is_the_full_estimate() -> None:
    from nefii.render.estimator import combine_pair, mean_of_pair
    n, wo, albedo, rough, lit, _ = shading_batch()
    material = Material(albedo.detach(), rough.detach())
    for N in (2, 5, 8):
        samples = sample_mis_directions(n, wo, rough.detach(), lit, N, torch.Generator().manual_seed(3))
        L_i = sg_eval(samples.wi, lit).detach()
        full = combine(samples, material, n, L_i)
        merged = mean_of_pair(combine_pair(samples, material, n, L_i), N)
        torch.testing.assert_close(merged.diffuse, full.diffuse, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(merged.specular, full.specular, rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="N >= 2"):
        samples = sample_mis_directions(n, wo, rough.detach(), lit, 1, torch.Generator().manual_seed(3))
        combine_pair(samples, material, n, sg_eval(samples.wi, lit).detach())


def test_the_pair_loss_has_no_variance_term_where_the_square_of_one_estimate_does() -> None:
    """At the right light level the expected gradient of the pair loss is zero (within its standard error);
    the squared error of one noisy estimate pushes the light down, by its variance (d Var / d s = 2 Var / s)."""
    from nefii.fit.losses import pair_distance
    from nefii.render.estimator import combine_pair
    env, B, N = environment(), NUM_POINTS, 4
    n, wo = NORMAL.expand(B, 3), view(30.0).expand(B, 3)
    material = Material(ALBEDO.expand(B, 3), torch.full((B,), 0.3, dtype=DTYPE))
    samples = sample_mis_directions(n, wo, material.roughness, env, N, torch.Generator().manual_seed(77))
    s = torch.ones((B, 1), dtype=DTYPE, requires_grad=True)       # one light scale per point: per-point gradients
    pair = combine_pair(samples, material, n, s.unsqueeze(-1) * sg_eval(samples.wi, env))
    full = 0.5 * (pair[0].rgb + pair[1].rgb)
    target = full.detach().mean(0, keepdim=True).expand(B, 3)
    g_pair, = torch.autograd.grad(pair_distance(pair[0].rgb, pair[1].rgb, target, "none") * B * 3, s, retain_graph=True)
    g_sq, = torch.autograd.grad((full - target).square().mean() * B * 3, s)
    m_pair, se_pair = mean_se(g_pair)
    m_sq, se_sq = mean_se(g_sq)
    variance = full.detach().var(0).sum()
    assert abs(float(m_pair)) < Z_MAX * float(se_pair), (m_pair, se_pair)
    assert float(m_sq) > Z_MAX * float(se_sq), (m_sq, se_sq)
    torch.testing.assert_close(m_sq.squeeze(), 2 * variance, rtol=0.1, atol=0.0)


@pytest.mark.parametrize("shared", [True, False])
def test_pick_lobe_is_the_count_of_cdf_entries_at_or_below_u(shared: bool) -> None:
    """``pick_lobe``'s binary search gives exactly the index that counting the CDF entries at or below ``u``
    times the total gives (the definition), zero-probability lobes and draws on a CDF step included, for
    probabilities shared by a point's draws ``(P, 1, K)`` and one set per draw ``(P, N, K)``."""
    g = torch.Generator().manual_seed(3)
    P, N, K = 64, 40, 128
    probs = torch.rand(P, 1 if shared else N, K, generator=g, dtype=DTYPE)
    probs[probs < 0.3] = 0.0                                      # lobes that must never be picked
    probs = probs / probs.sum(-1, keepdim=True)
    u = torch.rand(P, N, generator=g, dtype=DTYPE)
    cdf = probs.cumsum(-1)
    u[:, :8] = (cdf[:, :1, 40:48] / cdf[:, :1, -1:]).expand(P, 1, 8).reshape(P, 8)   # exactly on steps
    u[:, 8] = 0.0
    u[:, 9] = 1.0 - 1e-16
    expected = (cdf <= (u * cdf[..., -1]).unsqueeze(-1)).sum(-1).clamp_max(K - 1)
    k = pick_lobe(probs, u)
    assert k.shape == (P, N)
    assert torch.equal(k, expected)
    assert bool((probs.expand(P, N, K).gather(-1, k.unsqueeze(-1)) > 0).all())
