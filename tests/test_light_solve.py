"""The light solve (:mod:`nefii.fit.light_solve`): its design is the estimator, its solver is exact NNLS, and
a solve lowers Eq. 7's loss on pixels it did not read."""
from __future__ import annotations

import pytest
import torch

from fit_fixtures import write_rendered_scene
from nefii.fit.config import resolve_config
from nefii.fit.light_solve import (Quadratic, background_quadratic, linear_term, lobe_design, pixel_quadratic,
                                   solve_nonnegative)
from nefii.fit.losses import pair_distance
from nefii.fit.model import decode_material
from nefii.fit.path_trace import path_trace, sample_directions
from nefii.fit.policies import LightSolveSchedule
from nefii.fit.session import prepare_fit
from nefii.render.estimator import combine_pair
from nefii.render.sg import SGMixture


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=24, n_train=6, n_test=1)


def _trainer(scene, *overrides):
    return prepare_fit(resolve_config("tiny", ["light.init=uniform", *overrides]), scene).trainer


def _sg(env) -> SGMixture:
    sg = env()
    return SGMixture(sg.axis.detach(), sg.sharpness.detach(), sg.amplitude.detach())


def test_the_design_times_the_amplitudes_is_the_estimate(tiny_scene):
    trainer = _trainer(tiny_scene)
    model, px = trainer.model, trainer.pixels
    pts = px.points[torch.arange(0, len(px.points), 3)]
    with torch.no_grad():
        material = decode_material(model, pts.position, pts.lookup_normal, 0.5)
        samples = sample_directions(pts, material, model.env.light_sampler(), 8, torch.Generator().manual_seed(1))
        sg = _sg(model.env)
        design = lobe_design(pts, material, samples, sg, trainer.geometry, model.cache, trainer.transport)
        # the estimator's own incoming light for the same samples: V E(w) where a ray escapes, the cache where
        # it hits (as nefii.fit.path_trace does)
        from nefii.raycast.base import Rays, spawn_rays
        wi = samples.wi
        b, s = (samples.weight > 0).nonzero(as_tuple=True)
        rays = spawn_rays(pts.position[b], pts.geometric_normal[b], wi[b, s], trainer.cfg.ray_offset * trainer.geometry.scale)
        hit = trainer.geometry.intersect(Rays(rays.origins, rays.directions))
        L = torch.zeros_like(wi)
        L[b[~hit.valid], s[~hit.valid]] = model.env.radiance(wi[b, s][~hit.valid])
        L[b[hit.valid], s[hit.valid]] = model.cache(hit.position[hit.valid], hit.normal[hit.valid], -wi[b, s][hit.valid])
        assert bool(hit.valid.any()) and bool((~hit.valid).any())
        halves = combine_pair(samples, material, pts.normal, L)
    for h in range(2):
        linear = torch.einsum("pck,kc->pc", design.B[h], sg.amplitude) + design.c[h]
        torch.testing.assert_close(linear, halves[h].rgb, rtol=1e-3, atol=1e-5)   # float32 sums in other orders


def test_the_solver_is_nnls():
    scipy_optimize = pytest.importorskip("scipy.optimize")
    g = torch.Generator().manual_seed(0)
    P, K = 300, 12
    M = torch.rand(3, P, K, generator=g, dtype=torch.float64)
    y = torch.randn(3, P, generator=g, dtype=torch.float64) + 1.0   # noisy: some of the solution sits on x = 0
    q = Quadratic(M.transpose(1, 2) @ M / P, (M.transpose(1, 2) @ y.unsqueeze(-1)).squeeze(-1) / P)
    x = solve_nonnegative(q, torch.ones(3, K, dtype=torch.float64), iterations=5000)
    for c in range(3):
        ref, _ = scipy_optimize.nnls(M[c].numpy(), y[c].numpy())
        assert float((x[c] - torch.from_numpy(ref)).abs().max()) < 1e-4 * max(1.0, float(abs(ref).max()))


def test_terms_are_the_losses_they_stand_for():
    """Each quadratic, evaluated at any ``mu``, differs from its loss by a constant that does not depend on mu."""
    g = torch.Generator().manual_seed(2)
    P, K = 40, 5
    B1, B2 = torch.rand(P, 3, K, generator=g), torch.rand(P, 3, K, generator=g)
    c1, c2 = torch.rand(P, 3, generator=g), torch.rand(P, 3, generator=g)
    t, w = torch.rand(P, 3, generator=g), torch.rand(P, 3, generator=g) + 0.5
    from nefii.fit.light_solve import LobeDesign
    q = pixel_quadratic(LobeDesign((B1, B2), (c1, c2)), t, w)
    sg = SGMixture(torch.nn.functional.normalize(torch.randn(K, 3, generator=g), dim=-1), torch.rand(K, generator=g) * 5 + 1,
                   torch.rand(K, 3, generator=g))
    d = torch.nn.functional.normalize(torch.randn(30, 3, generator=g), dim=-1)
    tb = torch.rand(30, 3, generator=g)
    qb = background_quadratic(sg, d, tb, w[:30])
    p = torch.rand(K, generator=g)
    ql = linear_term(p)

    def value(quad, mu):   # sum over channels of mu^T A mu - 2 r^T mu
        mu = mu.double()
        return float((torch.einsum("kc,ckj,jc->c", mu, quad.A, mu) - 2 * torch.einsum("ck,kc->c", quad.r, mu)).sum())

    def loss(mu):
        a = torch.einsum("pck,kc->pc", B1, mu) + c1
        b = torch.einsum("pck,kc->pc", B2, mu) + c2
        pix = ((a - t) * w * (b - t) * w).mean(0).sum()
        env = (torch.exp(sg.sharpness * (d @ sg.axis.T - 1)) @ mu)
        bg = ((env - tb) * w[:30]).square().mean(0).sum()
        return float(pix + bg + (p[:, None] * mu).sum())

    mus = [torch.rand(K, 3, generator=g) * s for s in (0.1, 1.0, 3.0)]
    offsets = [loss(m) - value(q + qb + ql, m) for m in mus]
    assert max(offsets) - min(offsets) < 1e-4 * max(abs(o) for o in offsets + [1.0])


def test_a_solve_lowers_the_loss_on_pixels_it_did_not_read(tiny_scene):
    trainer = _trainer(tiny_scene, "light_solve_every=0", "light.init_radiance=5.0")
    model, px = trainer.model, trainer.pixels
    pts = px.points
    gen = lambda: torch.Generator().manual_seed(11)  # noqa: E731

    def loss() -> float:
        with torch.no_grad():
            material = decode_material(model, pts.position, pts.lookup_normal, 0.5)
            traced = path_trace(model, trainer.geometry, pts, material, 16, gen(), trainer.transport)
            return float(pair_distance(traced.pair[0].rgb, traced.pair[1].rgb, px.rgb, "log1p"))

    before = loss()
    amplitude = model.env().amplitude.detach().clone()
    trainer.solve_light(0.5)
    assert not torch.equal(model.env().amplitude.detach(), amplitude)
    assert loss() < 0.5 * before
    assert trainer.optimizer.state[model.env.log_amplitude] == {}


def test_the_schedule_and_the_configs():
    s = LightSolveSchedule(every=300, steps=3000)
    assert [k for k in range(3000) if s.due(k)] == list(range(300, 2850, 300))
    assert not any(LightSolveSchedule(0, 3000).due(k) for k in range(3000))
    assert resolve_config("cpu", []).light_solve_every > 0
    assert resolve_config("paper", []).light_solve_every == 0

def test_no_solve_for_a_loss_it_does_not_minimise(tiny_scene):
    assert not any(_trainer(tiny_scene, "loss=l1", "light_solve_every=1").light_solve.due(k) for k in range(20))
    assert any(_trainer(tiny_scene, "light_solve_every=1").light_solve.due(k) for k in range(20))


def test_a_linear_term_lives_on_its_coefficients_device():
    """The light prior's term is added to quadratics built on the fit's device (a CPU-only zero matrix broke the
    first solve of a CUDA fit); ``meta`` tensors check the device without a GPU."""
    q = linear_term(torch.ones(5, device="meta"))
    assert q.A.device.type == "meta" and q.r.device.type == "meta" and q.A.shape == (3, 5, 5)
    total = q + Quadratic(torch.zeros(3, 5, 5, dtype=torch.float64, device="meta"),
                          torch.zeros(3, 5, dtype=torch.float64, device="meta"))
    assert total.A.device.type == "meta"


def test_the_light_pdfs_lobe_values_light_the_escaped_rays_as_the_environment_does(tiny_scene):
    """``path_trace`` reads the escaped rays' radiance from the lobe values the light pdf kept
    (``DirectionSamples.light_lobes``): the estimate and its gradient to the light equal those of the same draws
    lit by ``model.env.radiance`` computed afresh."""
    trainer = _trainer(tiny_scene)
    model, px = trainer.model, trainer.pixels
    pts = px.points[torch.arange(0, len(px.points), 2)]
    material = decode_material(model, pts.position, pts.lookup_normal, 0.5)
    out = []
    for environment in (None, lambda w: model.env.radiance(w)):
        traced = path_trace(model, trainer.geometry, pts, material, 8, torch.Generator().manual_seed(3),
                            trainer.transport, environment=environment)
        grads = torch.autograd.grad(traced.radiance.rgb.square().sum(),
                                    (model.env.log_amplitude, model.env.log_sharpness, model.env.axis_raw),
                                    retain_graph=True)
        out.append((traced.radiance.rgb.detach(), grads))
    assert float(out[0][0].abs().max()) > 0
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-5, atol=1e-7)
    for a, b in zip(out[0][1], out[1][1]):
        assert float(a.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-9)
