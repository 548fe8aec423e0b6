"""The prior on the light where the object barely sees it: the coverage against closed forms, the prior's
gradient, and both environments' energies."""
import math

import numpy as np
import torch
import trimesh

from nefii.fields.environment import EnvmapEnvironment, SGEnvironment
from nefii.fit.light_prior import LightCoverage, direction_coverage, light_coverage, unseen_light_prior
from nefii.fit.losses import observed_loss
from nefii.fit.path_trace import PathTraced, RadianceEstimate, SurfacePoints
from nefii.raycast import MeshGeometry
from nefii.raycast.base import visible_cosines
from nefii.render.sg import fibonacci_sphere


def _quad(z: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _floor_points(n: int) -> SurfacePoints:
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(n, 2, generator=g) - 0.5                              # inside [-0.5, 0.5]^2
    pos = torch.cat([xy, torch.zeros(n, 1)], -1)
    up = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    return SurfacePoints(pos, up, up, up, up)


def test_coverage_of_an_open_floor_is_the_cosine():
    """Points on a floor that nothing shadows: ``c(d) = max(d_z, 0)``."""
    floor = MeshGeometry(*_quad(0.0, 1.0))
    d = fibonacci_sphere(200)
    c = direction_coverage(_floor_points(50), floor, d, ray_offset=1e-4)
    assert torch.allclose(c, d[:, 2].clamp_min(0.0), atol=1e-6)


def test_coverage_under_a_roof_is_zero_where_the_roof_blocks():
    """A wide roof at height 1 over the floor's points hides every direction steeper than its edge."""
    v0, f0 = _quad(0.0, 1.0)
    v1, f1 = _quad(1.0, 20.0)
    both = MeshGeometry(np.concatenate([v0, v1]), np.concatenate([f0, f1 + 4]))
    d = fibonacci_sphere(400)
    c = direction_coverage(_floor_points(50), both, d, ray_offset=1e-4)
    steep = d[:, 2] > math.sin(math.radians(10))                          # the roof edge is ~3 degrees up
    assert c[steep].abs().max() == 0.0
    flat = (d[:, 2] > 0.01) & (d[:, 2] < 0.03)
    assert flat.any() and (c[flat] > 0).all()                             # grazing light gets under the roof


def test_unseen_weight_is_zero_at_the_best_seen_direction_and_one_where_nothing_is_seen():
    floor = MeshGeometry(*_quad(0.0, 1.0))
    cov = light_coverage(_floor_points(300), floor, ray_offset=1e-4, seed=0)
    up, down = torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    assert cov.at(up).item() < 0.01 and cov.at(down).item() == 1.0
    # between: (1 - cos)^2 of the elevation
    side = torch.tensor([[math.cos(math.radians(30)), 0.0, math.sin(math.radians(30))]])
    assert abs(cov.at(side).item() - (1 - 0.5) ** 2) < 0.06


def test_seen_share_of_an_open_floor_is_the_cosine_of_the_elevation_and_zero_below_it():
    """``seen = c / max c``: what weighs a background pixel in Eq. 7's third term."""
    floor = MeshGeometry(*_quad(0.0, 1.0))
    cov = light_coverage(_floor_points(300), floor, ray_offset=1e-4, seed=0)
    elevations = torch.tensor([75.0, 45.0, 20.0, -20.0, -80.0])
    w = torch.stack([torch.cos(torch.deg2rad(elevations)), torch.zeros(5), torch.sin(torch.deg2rad(elevations))], -1)
    seen = cov.seen(w)
    expected = torch.sin(torch.deg2rad(elevations)).clamp_min(0.0)
    assert torch.allclose(seen, expected, atol=0.06)                      # the lattice is ~6 degrees apart
    assert seen[3:].abs().max() == 0.0
    assert torch.allclose(seen, 1.0 - cov.at(w).sqrt())                  # u = (1 - seen)^2


def test_the_sky_term_weighs_each_background_pixel():
    """Eq. 7's third term with per-pixel weights: zero weight drops a pixel, unit weights leave the term as it was."""
    env_bg = torch.tensor([[1.0, 1.0, 1.0], [3.0, 0.5, 2.0]])
    target_bg = torch.tensor([[2.0, 1.0, 1.0], [1.0, 0.5, 2.0]])
    traced = _traced_constant(4)
    rgb, cache = torch.full((4, 3), 0.5), torch.full((4, 3), 0.5)
    plain = observed_loss(traced, cache, rgb, env_bg, target_bg, "log1p", "l2_pair").background
    ones = observed_loss(traced, cache, rgb, env_bg, target_bg, "log1p", "l2_pair",
                         bg_weight=torch.ones(2)).background
    first = observed_loss(traced, cache, rgb, env_bg, target_bg, "log1p", "l2_pair",
                          bg_weight=torch.tensor([1.0, 0.0])).background
    err0 = (math.log1p(1.0) - math.log1p(2.0)) ** 2 / 3
    err1 = ((math.log1p(3.0) - math.log1p(1.0)) ** 2) / 3
    assert math.isclose(plain.item(), (err0 + err1) / 2, rel_tol=1e-5)
    assert math.isclose(ones.item(), plain.item(), rel_tol=1e-6)
    assert math.isclose(first.item(), err0 / 2, rel_tol=1e-5)


def _traced_constant(n: int) -> PathTraced:
    """A path-traced estimate of ``n`` pixels at 0.5 with its independent pair (what ``l2_pair`` reads)."""
    half = RadianceEstimate(torch.full((n, 3), 0.25), torch.full((n, 3), 0.0))
    none = torch.zeros(0, 3)
    return PathTraced(RadianceEstimate(torch.full((n, 3), 0.5), torch.zeros(n, 3)), (half, half),
                      SurfacePoints(none, none, none, none, none))


def test_prior_pulls_unseen_energy_only_and_ignores_the_light_s_scale():
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    cov = LightCoverage(dirs, torch.tensor([0.0, 1.0, 0.25]))
    energy = torch.tensor([5.0, 1.0, 2.0], requires_grad=True)
    value = unseen_light_prior(dirs, energy, cov, weight=0.1)
    assert math.isclose(value.item(), 0.1 * (1.0 + 0.5) / 8.0, rel_tol=1e-6)
    value.backward()
    assert torch.allclose(energy.grad, torch.tensor([0.0, 0.1 / 8.0, 0.025 / 8.0]))
    scaled = unseen_light_prior(dirs, energy.detach() * 10, cov, weight=0.1)
    assert math.isclose(scaled.item(), value.item(), rel_tol=1e-6)


def test_both_environments_report_their_energy_over_the_sphere():
    """A constant environment of radiance ``r`` holds ``4 pi r`` in either representation."""
    grid = EnvmapEnvironment(16, 32, init_radiance=0.7)
    d, e = grid.energy_atoms()
    assert d.shape == (16 * 32, 3) and math.isclose(e.sum().item(), 4 * math.pi * 0.7, rel_tol=1e-5)
    sg = SGEnvironment(num_lobes=128, init_radiance=0.7)
    axis, e = sg.energy_atoms()
    assert axis.shape == (128, 3) and math.isclose(e.sum().item(), 4 * math.pi * 0.7, rel_tol=1e-4)
    e.sum().backward()                                                    # differentiable in the amplitudes
    assert sg.log_amplitude.grad is not None and (sg.log_amplitude.grad > 0).all()


def test_visible_cosines_are_cosines_where_the_sky_is_open_and_zero_under_a_roof():
    """A point on the floor sees the upper hemisphere with its cosine; a roof above a second point hides
    what it covers; below the horizon everything is 0; the ray budget per call does not change the answer."""
    roof = trimesh.creation.box((0.4, 0.4, 0.02)).apply_translation((2.0, 0.0, 0.5))
    floor = trimesh.creation.box((6.0, 6.0, 0.02)).apply_translation((0.0, 0.0, -0.01))
    mesh = trimesh.util.concatenate([roof, floor])
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    x = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3)
    dirs = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, -0.5]]), dim=-1)
    v = visible_cosines(x, up, up, geometry, dirs, 1e-4)
    want = torch.tensor([[1.0, 2 ** -0.5, 0.0], [0.0, 2 ** -0.5, 0.0]])   # the roof covers the second point's zenith
    assert torch.allclose(v, want, atol=1e-6)
    assert torch.equal(visible_cosines(x, up, up, geometry, dirs, 1e-4, max_rays=1), v)
