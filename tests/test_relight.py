"""The relighting path tracer: white furnace, agreement with its simple sibling and with the one-bounce
MIS estimator, the env-map orientation (a mirror sphere reflects a single bright pixel where the
convention says), --rotate, --exposure, and the BSDF mixture sampler against its pdf."""
import math

import numpy as np
import pytest
import torch
import trimesh

from chi2 import SphericalBinning, chi2_test, sidak_level
from nefii.camera import intrinsics_from_fov, look_at, pixel_rays
from nefii.raycast import MeshGeometry, Rays, spawn_rays
from nefii.io.exr import write_exr
from nefii.relight.bsdf import pdf_bsdf, sample_bsdf, specular_probability
from nefii.relight.environment import load_environment
from nefii.render.envmap import Environment, rotate_z
from nefii.relight.pathtracer import PathSettings, trace_paths
from nefii.relight.pathtracer_reference import trace_paths_reference
from nefii.relight.render import render_relit
from nefii.render.brdf import BRDFModel, Material
from nefii.render.equirect import direction_to_uv, pixel_directions, uv_to_direction
from nefii.render.estimator import estimate_Lo

Z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def camera(azimuth_deg: float, elevation_deg: float, distance: float, fov_deg: float, res: int):
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = distance * torch.tensor([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)],
                                  dtype=torch.float64)
    return look_at(eye, torch.zeros(3, dtype=torch.float64), Z), intrinsics_from_fov(math.radians(fov_deg), res, res)


def centre_rays(c2w, K, res: int, repeat: int) -> Rays:
    o, d = pixel_rays(c2w, K, res, res)
    o = o.reshape(-1, 3).float().repeat_interleave(repeat, 0)
    d = d.reshape(-1, 3).float().repeat_interleave(repeat, 0)
    return Rays(o, d)


def room_with_skylight() -> tuple[MeshGeometry, torch.Tensor]:
    """The inside of a unit sphere whose top cap (z > 0.5) is cut away, faces turned inwards: every
    wall point sees mostly other walls, so most light arrives after several bounces. Returns the
    geometry and a camera inside, looking down at the floor."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    faces = s.faces[s.triangles_center[:, 2] < 0.5][:, ::-1]
    geometry = MeshGeometry(s.vertices, faces, normals=-s.vertices, threads=1)
    f64 = dict(dtype=torch.float64)
    c2w = look_at(torch.tensor([0.0, 0.0, 0.2], **f64), torch.tensor([0.1, 0.0, -1.0], **f64),
                  torch.tensor([1.0, 0.0, 0.0], **f64))
    return geometry, c2w


def sphere(subdivisions: int = 4) -> MeshGeometry:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    return MeshGeometry(s.vertices, s.faces, normals=s.vertices / 0.5, threads=1)


def sky(height: int = 16, width: int = 32, sun: bool = False) -> torch.Tensor:
    """A smooth sky over a dark ground (optionally a 2x2-pixel sun): non-constant, positive everywhere."""
    d = pixel_directions(height, width)
    z = d[..., 2:3]
    img = torch.where(z > 0, 0.6 + 0.8 * z, 0.15 + 0.05 * z) * torch.tensor([0.8, 0.9, 1.1])
    img = img + 0.5 * torch.exp(8.0 * ((d * torch.tensor([0.6, -0.5, 0.62])).sum(-1, keepdim=True) - 1.0))
    if sun:
        img[3:5, 10:12] = torch.tensor([40.0, 36.0, 30.0])
    return img


def constant(albedo, roughness: float, brdf: BRDFModel = BRDFModel()):
    a = torch.tensor(albedo, dtype=torch.float32)
    return lambda x, n: Material(a.expand(len(x), 3), torch.full((len(x),), roughness), brdf)


def mean_and_se(values: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    v = values.double().numpy()
    return v.mean(0), v.std(0, ddof=1) / math.sqrt(len(v))


# --------------------------------------------------------------------------- white furnace


def test_white_furnace_in_a_room_with_a_skylight():
    """Albedo 1, no specular lobe, environment 1 everywhere: every point reflects exactly 1 with all
    bounces (Russian roulette from the first), though three quarters of it arrive after several
    bounces; a bounce limit of 1 keeps only the light through the skylight."""
    geometry, c2w = room_with_skylight()
    K = intrinsics_from_fov(math.radians(100.0), 16, 16)
    rays = centre_rays(c2w, K, 16, 64)
    env = Environment.from_image(torch.ones(8, 16, 3))
    white = constant([1.0, 1.0, 1.0], 0.5, BRDFModel(diffuse="lambert"))        # Burley's is not energy-conserving
    gen = torch.Generator().manual_seed(0)
    full = trace_paths(rays, geometry, white, env, gen, PathSettings(max_bounces=64, rr_depth=1, specular=False))
    assert bool(full.hit.all())
    m, se = mean_and_se(full.radiance)
    assert np.all(np.abs(m - 1.0) < 4 * se) and np.all(se < 0.006), (m, se)
    one = trace_paths(rays, geometry, white, env, gen, PathSettings(max_bounces=1, specular=False))
    m1, _ = mean_and_se(one.radiance)
    assert np.all((0.15 < m1) & (m1 < 0.35)), m1


# --------------------------------------------------------------------------- against simpler estimators


def test_mis_path_tracer_agrees_with_cosine_only_sibling_over_several_bounces():
    """In the room, glossy non-white walls under a sky with a gradient and a broad lobe: the NEE + MIS
    + Russian roulette tracer and the cosine-only tracer estimate the same 4-bounce radiance."""
    geometry, c2w = room_with_skylight()
    res, spp = 16, 64
    K = intrinsics_from_fov(math.radians(100.0), res, res)
    rays = centre_rays(c2w, K, res, spp)
    env = Environment.from_image(sky())
    mat = constant([0.8, 0.6, 0.4], 0.45)
    settings = PathSettings(max_bounces=4, rr_depth=1)
    a = trace_paths(rays, geometry, mat, env, torch.Generator().manual_seed(1), settings)
    b = trace_paths_reference(rays, geometry, mat, env, torch.Generator().manual_seed(2), settings)
    assert torch.equal(a.hit, b.hit)
    # compare in four groups of pixels (image quadrants), every channel
    pix = torch.arange(res * res).repeat_interleave(spp)
    quadrant = ((pix // res) >= res // 2).long() * 2 + ((pix % res) >= res // 2).long()
    for q in range(4):
        sel = a.hit & (quadrant == q)
        ma, sa = mean_and_se(a.radiance[sel])
        mb, sb = mean_and_se(b.radiance[sel])
        assert np.all(np.abs(ma - mb) < 4.5 * np.hypot(sa, sb)), (q, ma, mb, sa, sb)


def test_one_bounce_path_tracer_matches_the_mis_estimator_with_visibility():
    """max_bounces = 1 on a convex sphere is the direct light: the one-bounce 3-strategy estimator
    of nefii.render.estimator with L_i = V E, at the same first hits, agrees in mean."""
    geometry = sphere()
    env = Environment.from_image(sky(sun=True))
    res, spp = 16, 32
    c2w, K = camera(40.0, 20.0, 3.0, 25.0, res)
    rays = centre_rays(c2w, K, res, spp)
    mat = constant([0.5, 0.3, 0.2], 0.3)
    pt = trace_paths(rays, geometry, mat, env, torch.Generator().manual_seed(3), PathSettings(max_bounces=1))
    pt_px = pt.radiance.reshape(res * res, spp, 3).mean(1)

    o, d = centre_rays(c2w, K, res, 1).origins, centre_rays(c2w, K, res, 1).directions
    hit = geometry.intersect(Rays(o, d))
    v = hit.valid
    x, n, ng = hit.position[v], hit.normal[v], hit.geometric_normal[v]

    def incoming(wi):
        shadow = spawn_rays(x.unsqueeze(1).expand_as(wi), ng.unsqueeze(1).expand_as(wi), wi, 1e-4 * geometry.scale)
        return env.radiance(wi) * (~geometry.occluded(shadow)).unsqueeze(-1)

    est = estimate_Lo(n, -d[v], mat(x, n), env, incoming, spp // 3 + 1, torch.Generator().manual_seed(4))
    diff = pt_px[v] - est.rgb                                 # same points: the signal cancels
    m, se = mean_and_se(diff)
    assert v.sum() > 100
    assert np.all(np.abs(m) < 4 * se), (m, se)
    assert np.all(np.abs(m) < 0.02 * est.rgb.mean(0).numpy())


# --------------------------------------------------------------------------- env-map orientation

H_ENV, W_ENV, RES = 64, 128, 64
LIGHT_PIXEL = (24, 54)   # row, col: about 22 deg above the horizon, azimuth about 28 deg


def bright_pixel_map() -> torch.Tensor:
    img = torch.full((H_ENV, W_ENV, 3), 1e-4)
    img[LIGHT_PIXEL] = 1e5
    return img


def light_direction() -> torch.Tensor:
    i, j = LIGHT_PIXEL
    return uv_to_direction(torch.tensor((j + 0.5) / W_ENV, dtype=torch.float64),
                           torch.tensor((i + 0.5) / H_ENV, dtype=torch.float64))


def expected_reflection_pixel(c2w, K, light: torch.Tensor) -> tuple[int, int]:
    """The pixel whose ray, mirrored by the analytic sphere (radius 0.5 at the origin), points closest
    to ``light``: where a mirror ball shows that direction."""
    o, d = pixel_rays(c2w, K, RES, RES)
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 0.25)
    t = -b - disc.clamp_min(0).sqrt()
    p = o + t.unsqueeze(-1) * d
    n = p / 0.5
    r = d - 2 * (d * n).sum(-1, keepdim=True) * n
    score = torch.where(disc > 0, (r * light).sum(-1), torch.tensor(-2.0, dtype=torch.float64))
    k = int(score.argmax())
    return k // RES, k % RES


def brightest_pixel(env: Environment, seed: int = 0) -> tuple[int, int]:
    c2w, K = mirror_camera()
    mirror = constant([0.0, 0.0, 0.0], 0.089)
    img = render_relit(sphere(5), mirror, env, c2w, K, RES, RES, 4, torch.Generator().manual_seed(seed),
                       PathSettings(max_bounces=1, f0=1.0))
    k = int(img.rgb.sum(-1).argmax())
    return k // RES, k % RES


def mirror_camera():
    return camera(60.0, 10.0, 3.0, 24.0, RES)


def chebyshev(a, b) -> int:
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]))


def test_mirror_sphere_reflects_a_single_bright_pixel_where_the_convention_says(tmp_path):
    """The map goes through a file (EXR, row 0 = +Z) and nefii.render.equirect's mapping; the brightest
    pixel of the render is within 2 pixels of the mirror geometry's prediction, and far from where
    a map flipped left-right (phi -> -phi) or upside down would put it."""
    write_exr(tmp_path / "one.exr", bright_pixel_map().numpy())
    env = load_environment(tmp_path / "one.exr")
    light = light_direction()
    assert env.radiance(light.float().unsqueeze(0))[0, 0] == 1e5
    c2w, K = mirror_camera()
    want = expected_reflection_pixel(c2w, K, light)
    got = brightest_pixel(env)
    assert chebyshev(got, want) <= 2, (got, want)
    for wrong in (light * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64),
                  light * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)):
        assert chebyshev(got, expected_reflection_pixel(c2w, K, wrong)) > 6


def test_rotate_90_moves_the_reflection_by_90_degrees_counter_clockwise(tmp_path):
    write_exr(tmp_path / "one.exr", bright_pixel_map().numpy())
    env = load_environment(tmp_path / "one.exr", rotate=90.0)
    light = light_direction()
    turned = torch.stack([-light[1], light[0], light[2]])              # azimuth + 90 deg
    c2w, K = mirror_camera()
    want = expected_reflection_pixel(c2w, K, turned)
    got = brightest_pixel(env, seed=1)
    assert chebyshev(got, want) <= 2, (got, want)
    assert chebyshev(got, expected_reflection_pixel(c2w, K, light)) > 6


def test_rotation_is_exact_and_keeps_the_sampling_density():
    g = torch.Generator().manual_seed(5)
    env0 = Environment.from_image(sky(sun=True))
    env = Environment.from_image(sky(sun=True), rotation=37.0)
    w = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g), dim=-1)
    turned = rotate_z(w, 37.0)
    u0, _ = direction_to_uv(w)
    u1, _ = direction_to_uv(turned)
    assert torch.allclose(torch.remainder(u0 - u1, 1.0), torch.full_like(u0, 37.0 / 360.0), atol=1e-5)
    assert torch.allclose(env.radiance(turned), env0.radiance(w))
    assert torch.allclose(env.pdf_direction(turned), env0.pdf_direction(w), rtol=1e-4)
    u = torch.rand(1000, 2, generator=g)
    assert torch.allclose(env.sample_direction(u), rotate_z(env0.sample_direction(u), 37.0), atol=1e-6)


def test_exposure_plus_one_doubles_the_image(tmp_path):
    write_exr(tmp_path / "sky.exr", sky(sun=True).numpy())
    env0 = load_environment(tmp_path / "sky.exr")
    env1 = load_environment(tmp_path / "sky.exr", exposure=1.0)
    assert torch.equal(env1.image, 2.0 * env0.image)
    c2w, K = camera(0.0, 30.0, 3.0, 30.0, 12)
    mat = constant([0.6, 0.5, 0.4], 0.4)
    a = render_relit(sphere(3), mat, env0, c2w, K, 12, 12, 4, torch.Generator().manual_seed(7))
    b = render_relit(sphere(3), mat, env1, c2w, K, 12, 12, 4, torch.Generator().manual_seed(7))
    assert a.rgb.max() > 0
    assert torch.allclose(b.rgb, 2.0 * a.rgb, rtol=1e-5, atol=1e-7)
    assert torch.equal(a.coverage, b.coverage)


# --------------------------------------------------------------------------- the BSDF mixture sampler


@pytest.mark.parametrize("albedo, roughness, view_deg", [(0.5, 0.3, 40.0), (0.05, 0.6, 70.0)])
def test_bsdf_mixture_sampler_chi2(albedo, roughness, view_deg):
    theta = math.radians(view_deg)
    wo = torch.tensor([math.sin(theta) * math.cos(0.7), math.sin(theta) * math.sin(0.7), math.cos(theta)],
                      dtype=torch.float64)
    m = Material(torch.full((3,), albedo, dtype=torch.float64), torch.tensor(roughness, dtype=torch.float64))
    q = specular_probability(m, wo)
    alpha = torch.tensor(roughness**2, dtype=torch.float64)
    assert 0.2 <= float(q) <= 0.9
    result = chi2_test(lambda u: sample_bsdf(wo, alpha, q, u), lambda w: pdf_bsdf(wo, w, alpha, q),
                       SphericalBinning((0.0, 0.0, 1.0), kappa=1.0, n_theta=24, n_phi=24),
                       dim_u=3, num_samples=200_000, seed=11)
    assert result.p_value > sidak_level(0.01, 2), result.describe()
