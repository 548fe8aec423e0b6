"""The geometry stage: NeuS volume rendering math, normalisation, SDF networks, sphere tracing against
Embree, marching cubes, signed distances of a mesh, and ``nefii geometry`` end to end at a tiny size."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
import trimesh

from nefii.camera import intrinsics_from_fov, look_at, pixel_rays
from nefii.cli.main import main
from nefii.data.scene import Cameras
from nefii.errors import InputError
from nefii.fields.encodings import HashGrid
from nefii.raycast import MeshGeometry
from nefii.raycast.base import Rays
from nefii.sdf.config import geometry_config_from_dict, resolve_geometry_config
from nefii.sdf.extract import extract_mesh
from nefii.sdf.from_mesh import inside_by_parity, mesh_signed_distances
from nefii.sdf.metrics import mesh_distance, seen_by
from nefii.sdf.networks import SDFNetwork
from nefii.sdf.normalization import Normalization, look_at_center, normalization_from_cameras
from nefii.sdf.outputs import load_sdf
from nefii.sdf.trace import SDFGeometry
from nefii.sdf.losses import level_set_area, normal_variation
from nefii.sdf.model import NeuSModel
from nefii.sdf.train import ImageObjective, draw_rays, uniform_in_ball
from nefii.sdf.volume import (composite_weights, neus_alpha, sample_pdf, sphere_bounds, stratified_depths,
                              upsample_depths)

# --------------------------------------------------------------------------- volume rendering math


def test_geometry_config_round_trips_and_rejects_unknown_fields():
    cfg = resolve_geometry_config("paper", ["steps=7", "sdf.hidden=32"])
    assert cfg.preset == "paper" and cfg.steps == 7 and cfg.sdf.hidden == 32
    assert geometry_config_from_dict(json.loads(json.dumps(dataclasses.asdict(cfg)))) == cfg
    assert resolve_geometry_config("cpu", []) != cfg
    for bad, err in (("sdf.nope=1", KeyError), ("sdf=3", KeyError), ("steps", ValueError), ("steps=x", ValueError),
                     ("foreground_rays=1.5", ValueError), ("area_weight=-0.1", ValueError),
                     ("normal_smoothness_start=2", ValueError), ("view_freqs=-1", ValueError)):
        with pytest.raises(err):
            resolve_geometry_config("cpu", [bad])
    with pytest.raises(KeyError):
        resolve_geometry_config("huge", [])


def test_the_gpu_preset_is_the_cpu_method_with_more_rays_a_step():
    cpu, gpu = resolve_geometry_config("cpu", []), resolve_geometry_config("gpu", [])
    assert gpu.preset == "gpu" and gpu.batch_rays == 8 * cpu.batch_rays and gpu.steps == cpu.steps // 3
    assert gpu.batch_rays * gpu.steps > 2 * cpu.batch_rays * cpu.steps, "more rays in all, in fewer steps"
    same = {k: v for k, v in dataclasses.asdict(gpu).items() if k not in ("preset", "batch_rays", "steps")}
    assert same == {k: v for k, v in dataclasses.asdict(cpu).items() if k in same}, "networks and priors as cpu"


def test_sphere_bounds_are_the_analytic_entry_and_exit():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.5, -3.0], [0.0, 2.0, -3.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3)
    near, far, hit = sphere_bounds(o, d)
    assert hit.tolist() == [True, True, False, True]
    torch.testing.assert_close(near[:2], torch.tensor([2.0, 3.0 - math.sqrt(0.75)]))
    torch.testing.assert_close(far[:2], torch.tensor([4.0, 3.0 + math.sqrt(0.75)]))
    assert float(near[3]) == 0.0 and float(far[3]) == pytest.approx(1.0)


def test_stratified_depths_are_sorted_and_one_per_bin():
    near, far = torch.tensor([0.5, 1.0]), torch.tensor([1.5, 3.0])
    z = stratified_depths(near, far, 8, torch.Generator().manual_seed(0))
    assert bool((z[:, 1:] > z[:, :-1]).all())
    bins = ((z - near[:, None]) / (far - near)[:, None] * 8).floor()
    assert bins.tolist() == [list(range(8))] * 2


def _plane_render(inv_s: float, n: int = 512):
    """A ray along +z through the plane z = 1 (SDF 1 - z, facing the ray), samples from 0 to 2."""
    z = torch.linspace(0.0, 2.0, n + 1).unsqueeze(0)
    mids, deltas = 0.5 * (z[:, 1:] + z[:, :-1]), z[:, 1:] - z[:, :-1]
    sdf = 1.0 - mids
    cos = torch.full_like(sdf, -1.0)
    w = composite_weights(neus_alpha(sdf, cos, deltas, inv_s))
    return mids, w


@pytest.mark.parametrize("inv_s", [20.0, 200.0])
def test_neus_weights_of_a_plane_peak_at_the_surface_and_sum_to_one(inv_s):
    mids, w = _plane_render(inv_s)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-3)
    depth = float((w * mids).sum())
    assert depth == pytest.approx(1.0, abs=2.0 / inv_s)          # unbiased: the expected depth is the surface
    assert float(mids[0, w.argmax()]) == pytest.approx(1.0, abs=2.0 / 512 + 1e-6)


def test_sample_pdf_follows_the_weights():
    edges = torch.linspace(0.0, 1.0, 11).unsqueeze(0)
    w = torch.zeros(1, 10)
    w[0, 3] = 1.0
    s = sample_pdf(edges, w, 64)
    assert float(((s >= 0.3) & (s <= 0.4)).float().mean()) > 0.95


def test_upsampling_puts_new_samples_near_the_surface():
    z = torch.linspace(0.0, 2.0, 33).unsqueeze(0)
    new = upsample_depths(z, 1.0 - z, 16, inv_s=64.0)
    assert float((new - 1.0).abs().max()) < 0.1


# --------------------------------------------------------------------------- normalisation


def ring_cameras(n: int = 8, res: int = 48, center=(0.3, -0.2, 0.1), dist: float = 3.0) -> Cameras:
    c = torch.tensor(center, dtype=torch.float64)
    c2w = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = c + dist * torch.tensor([math.cos(a), math.sin(a), 0.4 + 0.3 * (k % 2)], dtype=torch.float64)
        c2w.append(look_at(eye, c, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)))
    K = intrinsics_from_fov(math.radians(40.0), res, res)
    return Cameras(K.expand(n, 3, 3).clone(), torch.stack(c2w), res, res)


def sphere_masks(cams: Cameras, center, radius: float) -> torch.Tensor:
    geo = MeshGeometry(*(lambda m: (m.vertices, m.faces))(
        trimesh.creation.icosphere(subdivisions=4, radius=radius).apply_translation(center)))
    masks = []
    for v in range(len(cams)):
        o, d = pixel_rays(cams.c2w[v], cams.K[v], cams.height, cams.width)
        masks.append(geo.intersect(Rays(o.reshape(-1, 3).float(), d.reshape(-1, 3).float())).valid.reshape(
            cams.height, cams.width))
    return torch.stack(masks)


def test_foreground_biased_rays_are_reweighted_to_the_mean_over_all_pixels():
    gen = torch.Generator().manual_seed(0)
    pixels = 1000
    mask = torch.zeros(pixels, dtype=torch.bool)
    mask[::7] = True                                      # 143 foreground pixels
    value = torch.rand(pixels, generator=gen) + 2.0 * mask.float()
    i, w = draw_rays(pixels, mask, mask.nonzero().squeeze(-1), 200_000, 0.75, gen, torch.device("cpu"))
    assert mask[i].float().mean() == pytest.approx(0.75 + 0.25 * 143 / pixels, abs=0.01)
    assert float((w * value[i]).sum() / w.sum()) == pytest.approx(float(value.mean()), rel=0.01)
    # the foreground alone is still drawn uniformly: every foreground pixel about equally often
    counts = torch.bincount(i[mask[i]], minlength=pixels)[mask].float()
    assert counts.std() / counts.mean() < 0.05
    j, none = draw_rays(pixels, None, None, 64, 0.75, gen, torch.device("cpu"))
    assert none is None and len(j) == 64


def test_the_cameras_look_at_center_is_found():
    cams = ring_cameras()
    torch.testing.assert_close(look_at_center(cams.c2w), torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64))


def test_normalisation_from_masks_is_the_visual_hulls_bounding_sphere():
    cams = ring_cameras()
    center, r = (0.1, 0.0, 0.2), 0.4                      # off the look-at point on purpose
    norm = normalization_from_cameras(cams, sphere_masks(cams, center, r), margin=1.0)
    assert np.allclose(norm.center, center, atol=0.08)
    assert r <= norm.radius <= r * 1.45                      # a visual hull from 8 views is a bit larger
    x = torch.randn(10, 3, dtype=torch.float64)
    torch.testing.assert_close(norm.to_world(norm.to_unit(x)), x)


def sphere_hits(cams: Cameras, view: int, center, radius: float) -> torch.Tensor:
    """(H, W) whether each pixel's ray through its centre meets the sphere."""
    o, d = pixel_rays(cams.c2w[view], cams.K[view], cams.height, cams.width)
    oc = o.double() - torch.tensor(center, dtype=torch.float64)
    d = d.double() / d.double().norm(dim=-1, keepdim=True)
    tc = -(oc * d).sum(-1)
    return (oc + tc.unsqueeze(-1) * d).norm(dim=-1) <= radius


def test_normalisation_without_masks_holds_the_nearest_views_whole_frame():
    cams = ring_cameras()
    norm = normalization_from_cameras(cams, None)
    assert np.allclose(norm.center, (0.3, -0.2, 0.1), atol=1e-6)
    corner = math.atan(math.sqrt(2) * math.tan(math.radians(20.0)))      # 40 degrees across the square frame
    assert norm.radius == pytest.approx(3.0 * math.sqrt(1 + 0.4**2) * math.sin(corner), rel=1e-6)
    nearest = 0                                   # the ring's even views sit lower, nearer the centre
    assert sphere_hits(cams, nearest, norm.center, norm.radius).all(), "every pixel of the nearest view"
    shrunk = sphere_hits(cams, nearest, norm.center, 0.97 * norm.radius)
    assert not shrunk[0, 0] and not shrunk[-1, -1] and shrunk[24, 24], "the corners are what sets it"


def test_normalisation_files_round_trip_and_bad_ones_are_input_errors(tmp_path):
    n = Normalization((1.0, 2.0, 3.0), 0.5)
    n.save(tmp_path / "n.json")
    assert Normalization.load(tmp_path / "n.json") == n
    (tmp_path / "bad.json").write_text('{"center": [1, 2], "radius": -1}')
    with pytest.raises(InputError, match="bad.json"):
        Normalization.load(tmp_path / "bad.json")
    cams = ring_cameras(n=4)
    with pytest.raises(InputError, match="carve away everything"):
        normalization_from_cameras(cams, torch.zeros(4, 48, 48, dtype=torch.bool))


# --------------------------------------------------------------------------- SDF network, marching cubes, tracing


def bumpy_sdf(seed: int = 0) -> SDFNetwork:
    """A small SDF network: the initial sphere (radius 0.5) plus a smooth random bump field."""
    torch.manual_seed(seed)
    net = SDFNetwork(HashGrid(4, 2, 12, 4, 16, init_scale=0.5), 16, 1, 4)
    with torch.no_grad():
        net.net[-1].weight[0].normal_(0.0, 0.02)
    return net


def test_the_sdf_network_starts_as_an_exact_sphere():
    torch.manual_seed(0)
    net = SDFNetwork(HashGrid(4, 2, 12, 4, 16), 16, 1, 4, init_radius=0.5)
    u = torch.randn(500, 3) * 0.4
    sdf, grad, feat = net.with_gradient(u, create_graph=False)
    torch.testing.assert_close(sdf, u.norm(dim=-1) - 0.5)
    torch.testing.assert_close(grad.norm(dim=-1), torch.ones(500))
    assert feat.shape == (500, 4)


def test_the_minimal_surface_prior_measures_the_level_sets_area():
    """``mean exp(-tau |f|)`` over the ball for exact spheres: ``(2 / tau) A / V``, so a sphere of twice
    the radius scores four times as much."""
    gen = torch.Generator().manual_seed(0)
    u = uniform_in_ball(400_000, gen, torch.device("cpu"))
    tau = 200.0
    a = {r: float(level_set_area(u.norm(dim=-1) - r, tau)) for r in (0.3, 0.6)}
    for r, value in a.items():
        assert value == pytest.approx((2 / tau) * 4 * math.pi * r**2 / (4 / 3 * math.pi), rel=0.05)
    assert a[0.6] / a[0.3] == pytest.approx(4.0, rel=0.05)


def test_the_normal_prior_measures_curvature_along_the_surface():
    """On the network's initial exact sphere of radius r, the normal turns by |t| / r over a tangent
    step t: halving r doubles the prior; a step along the normal (across a wall) would change nothing."""
    gen = torch.Generator().manual_seed(0)
    values = {}
    for r in (0.25, 0.5):
        torch.manual_seed(0)
        net = SDFNetwork(HashGrid(4, 2, 12, 4, 16), 16, 1, 4, init_radius=r)
        d = torch.randn(4000, 3, generator=gen)
        x = r * d / d.norm(dim=-1, keepdim=True)
        values[r] = float(normal_variation(net, x, 0.01, gen).detach())
    assert values[0.25] / values[0.5] == pytest.approx(2.0, rel=0.1)
    # std 0.01 per axis in the 2-d tangent plane: E|t| = 0.01 sqrt(pi / 2); dn = t / r points in a
    # uniformly random direction, whose L1 norm is 3 E|cos| = 1.5 times its length on average
    assert values[0.5] == pytest.approx(0.01 * math.sqrt(math.pi / 2) / 0.5 * 1.5, rel=0.05)


def test_coarse_to_fine_switches_hash_levels_on_in_order():
    """With ``active`` levels only the coarse levels reach the MLP: perturbing a finer level's table
    changes nothing until that level is on; ``None`` turns all on (what is saved)."""
    net = bumpy_sdf()
    grid = net.encoding
    u = torch.rand(300, 3) * 1.6 - 0.8
    net.set_active_levels(2.5)
    torch.testing.assert_close(net.level_weights, torch.tensor([1.0, 1.0, 0.5, 0.0]))
    before = net.sdf(u)
    with torch.no_grad():
        grid.table[int(grid.offset[3]):] += 1.0                       # level 3: off, so no effect
    torch.testing.assert_close(net.sdf(u), before)
    with torch.no_grad():
        grid.table[int(grid.offset[2]):int(grid.offset[3])] += 1.0    # level 2: half on
    assert not torch.allclose(net.sdf(u), before)
    net.set_active_levels(None)
    torch.testing.assert_close(net.level_weights, torch.ones(4))


def test_marching_cubes_of_the_initial_sphere_is_that_sphere_wound_outwards():
    torch.manual_seed(0)
    net = SDFNetwork(HashGrid(4, 2, 12, 4, 16), 16, 1, 4, init_radius=0.5)
    norm = Normalization((1.0, -2.0, 0.5), 2.0)
    mesh = extract_mesh(net, norm, 64)
    ref = trimesh.creation.icosphere(subdivisions=5, radius=1.0).apply_translation((1.0, -2.0, 0.5))
    dist = mesh_distance(mesh, ref, samples=20000)
    assert dist.chamfer_rel < 0.005, dist                       # the 20k-sample floor is ~0.0035
    assert dist.missed == 0.0
    assert mesh.volume > 0 and mesh.volume == pytest.approx(4 / 3 * math.pi, rel=0.02)


def test_missed_is_the_share_of_the_reference_the_prediction_lacks():
    """A reference of two equal spheres far apart against a prediction of one of them: half of the
    reference's surface is missed, none of it when the prediction has both; a prediction displaced by
    less than the threshold misses nothing, one displaced by more misses everything."""
    a = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    b = a.copy().apply_translation((5.0, 0.0, 0.0))
    both = trimesh.util.concatenate([a, b])
    assert mesh_distance(a, both, samples=20000).missed == pytest.approx(0.5, abs=0.02)
    assert mesh_distance(both, both, samples=20000).missed == 0.0
    diag = float(np.linalg.norm(a.bounds[1] - a.bounds[0]))
    near = a.copy().apply_translation((0.01 * diag, 0.0, 0.0))
    assert mesh_distance(near, a, samples=20000).missed < 0.01
    shrunk = a.copy().apply_scale(1.0 - 0.05 * diag)
    assert mesh_distance(shrunk, a, samples=20000).missed > 0.99


def test_the_covered_normal_error_is_the_tilt_where_the_prediction_lies_and_ignores_what_it_lacks():
    """A grid of a unit square tilted by 3 degrees about its middle against the flat square: every normal is 3
    degrees off, so the median over the covered part is 3 (the tilted edges, farther than 1% of the diagonal,
    are left out); a second, missing square adds to ``missed`` and not to the median."""
    flat = trimesh.creation.box((1.0, 1.0, 1e-3)).subdivide().subdivide().subdivide()
    tilted = flat.copy().apply_transform(trimesh.transformations.rotation_matrix(math.radians(3.0), (1, 0, 0)))
    d = mesh_distance(tilted, flat, samples=40000)
    assert d.normal_median_covered_deg == pytest.approx(3.0, abs=0.05)
    assert mesh_distance(flat, flat, samples=40000).normal_median_covered_deg < 0.01
    far = flat.copy().apply_translation((0.0, 0.0, 3.0))
    d2 = mesh_distance(tilted, trimesh.util.concatenate([flat, far]), samples=40000)
    assert d2.missed > 0.45 and d2.normal_median_covered_deg == pytest.approx(3.0, abs=0.05)


def _cameras_above(n: int, elevations: tuple[float, float], distance: float = 6.0) -> Cameras:
    """``n`` cameras looking at the origin from ``distance``, elevations spread between the two (degrees)."""
    c2w, K = [], intrinsics_from_fov(math.radians(40.0), 64, 64)
    for i in range(n):
        az, el = 2 * math.pi * i / n, math.radians(elevations[0] + (elevations[1] - elevations[0]) * (i % 3) / 2)
        eye = torch.tensor([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)],
                           dtype=torch.float64) * distance
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        c2w.append(look_at(eye, torch.zeros(3, dtype=torch.float64), up))
    return Cameras(K.expand(n, 3, 3).clone(), torch.stack(c2w), 64, 64)


def test_the_seen_share_leaves_out_what_no_camera_sees():
    """A cube seen from above (elevations 20-60 degrees): its bottom face, a sixth of its area, is seen by no
    camera, and a box standing on the cube's top hides the part of the top under it. A prediction without the
    bottom face misses a sixth of the cube (less the band along its edges that lies within the threshold of the
    sides) and nothing of what the cameras see; one without the top face misses a fifth of what they see."""
    cube = trimesh.creation.box((1.0, 1.0, 1.0)).subdivide().subdivide()
    cams = _cameras_above(12, (20.0, 60.0))
    d = mesh_distance(cube, cube, samples=30000, cameras=cams)
    assert d.seen == pytest.approx(5 / 6, abs=0.01) and d.missed_seen == 0.0
    faces = cube.face_normals
    no_bottom = cube.submesh([np.flatnonzero(faces[:, 2] > -0.5)], append=True)
    no_top = cube.submesh([np.flatnonzero(faces[:, 2] < 0.5)], append=True)
    inner = (1 - 2 * 0.02 * math.sqrt(3)) ** 2                 # a face's share farther than 2% of the diagonal
    d = mesh_distance(no_bottom, cube, samples=30000, cameras=cams)
    assert d.missed == pytest.approx(inner / 6, abs=0.01) and d.missed_seen < 0.002
    d = mesh_distance(no_top, cube, samples=30000, cameras=cams)
    assert d.missed_seen == pytest.approx(inner / 5, abs=0.01)
    lid = trimesh.creation.box((0.5, 0.5, 0.5)).apply_translation((0.0, 0.0, 0.75))
    stacked = trimesh.util.concatenate([cube, lid])
    seen = seen_by(cube.triangles_center, faces, stacked, cams)
    top = faces[:, 2] > 0.5
    reach = np.abs(cube.triangles_center[:, :2]).max(1)
    assert not seen[top & (reach < 0.25)].any() and seen[top & (reach > 0.3)].all()
    assert not seen[faces[:, 2] < -0.5].any() and seen[np.abs(faces[:, 2]) < 0.5].all()


def test_sphere_tracing_agrees_with_embree_on_the_extracted_mesh():
    """Hit or miss the same for nearly every ray, and the distance within one marching-cubes voxel."""
    net = bumpy_sdf()
    norm = Normalization((0.2, 0.1, -0.3), 1.5)
    res = 128
    mesh = extract_mesh(net, norm, res, min_component=0.0)
    embree = MeshGeometry(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    traced = SDFGeometry(net, norm)
    g = torch.Generator().manual_seed(1)
    o = torch.tensor(norm.center) + torch.nn.functional.normalize(torch.randn(3000, 3, generator=g), dim=-1) * 3.0
    target = torch.tensor(norm.center) + torch.randn(3000, 3, generator=g) * 0.5
    d = torch.nn.functional.normalize(target - o, dim=-1)
    a, b = traced.intersect(Rays(o, d)), embree.intersect(Rays(o, d))
    assert 0.2 < float(b.valid.float().mean()) < 0.95
    both = a.valid & b.valid
    agree = float((a.valid == b.valid).float().mean())
    assert agree > 0.99, agree                                   # disagreements only at grazing silhouettes
    voxel = 2.0 / (res - 1) * norm.radius
    err = (a.t[both] - b.t[both]).abs()
    assert float(err.quantile(0.99)) < voxel, (float(err.max()), voxel)
    assert a.features is not None and a.features.shape == (3000, 4)
    cos = (a.normal[both] * b.geometric_normal[both]).sum(-1)
    assert float(cos.median()) > 0.98


def test_sphere_tracing_respects_t_max_and_starts_from_surfaces():
    net = bumpy_sdf()
    norm = Normalization((0.0, 0.0, 0.0), 1.0)
    geo = SDFGeometry(net, norm)
    o = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    full = geo.intersect(Rays(o, d))
    assert bool(full.valid.all())
    short = geo.intersect(Rays(o, d, t_max=full.t - 0.05))
    assert not bool(short.valid.any())
    # a secondary ray leaving the surface outwards does not hit its own start
    x, n = full.position[:1], full.normal[:1]
    assert not bool(geo.occluded(Rays(x + 1e-3 * n, n)).any())


# --------------------------------------------------------------------------- signed distances of a mesh


def test_inside_by_parity_matches_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    geo = MeshGeometry(sphere.vertices, sphere.faces)
    pts = np.random.default_rng(0).uniform(-0.8, 0.8, size=(4000, 3))
    r = np.linalg.norm(pts, axis=-1)
    clear = np.abs(r - 0.5) > 0.01                                # away from the faceting
    assert np.array_equal(inside_by_parity(geo, pts)[clear], (r < 0.5)[clear])


def test_mesh_signed_distances_match_the_analytic_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    norm = Normalization((0.0, 0.0, 0.0), 0.8)
    sd = mesh_signed_distances(sphere, norm, 4000, surface_samples=200_000)
    exact = (sd.points.norm(dim=-1) * 0.8 - 0.5) / 0.8
    err = (sd.sdf - exact).abs()
    assert float(err.quantile(0.99)) < 0.01
    assert float(sd.points.norm(dim=-1).max()) < 1.3


# --------------------------------------------------------------------------- nefii geometry end to end


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from fit_fixtures import write_rendered_scene
    return write_rendered_scene(tmp_path_factory.mktemp("gscene"), res=24, n_train=8, n_test=2)


def _geometry(scene, out, *extra):
    return main(["geometry", str(scene), "--out", str(out), "--preset", "tiny", "--quiet",
                 "--set", "threads=1", *extra])


@pytest.mark.parametrize("masks", ["on", "off"])
def test_geometry_runs_end_to_end_with_and_without_masks(tiny_scene, tmp_path, masks):
    out = tmp_path / "geo"
    assert _geometry(tiny_scene, out, "--masks", masks) == 0
    for name in ("sdf.pt", "mesh.ply", "normalization.json", "config.json", "geometry_stats.json"):
        assert (out / name).is_file(), name
    stats = json.loads((out / "geometry_stats.json").read_text())
    assert stats["mesh_faces"] > 0 and ("with masks" in stats["source"]) == (masks == "on")
    loaded = load_sdf(out)
    mesh = trimesh.load(out / "mesh.ply", force="mesh")
    # the mesh is in world coordinates: inside the normalisation sphere
    r = np.linalg.norm(np.asarray(mesh.vertices) - np.asarray(loaded.normalization.center), axis=-1)
    assert r.max() <= loaded.normalization.radius * 1.01
    # and the loaded SDF is the trained one: zero on its own mesh's vertices (within a voxel)
    u = loaded.normalization.to_unit(torch.from_numpy(np.asarray(mesh.vertices)).float())
    assert float(loaded.sdf.sdf(u).abs().max()) < 2.0 / (loaded.config.mesh_resolution - 1) * 2


def test_the_gpu_preset_on_the_cpu_is_warned_about(tiny_scene, tmp_path, capsys):
    assert main(["geometry", str(tiny_scene), "--out", str(tmp_path / "geo"), "--preset", "gpu", "--quiet",
                 "--device", "cpu", "--set", "threads=1", "--set", "steps=2", "--set", "batch_rays=32",
                 "--set", "mesh_resolution=32"]) == 0
    assert "the gpu preset on the CPU" in capsys.readouterr().err


def test_geometry_from_a_mesh_recovers_it(tiny_scene, tmp_path):
    out = tmp_path / "geo"
    assert _geometry(tiny_scene, out, "--from-mesh", str(tiny_scene / "mesh.ply"), "--set", "steps=300",
                     "--set", "mesh_resolution=64") == 0
    pred = trimesh.load(out / "mesh.ply", force="mesh")
    ref = trimesh.load(tiny_scene / "mesh.ply", force="mesh")
    assert mesh_distance(pred, ref, samples=20000).chamfer_rel < 0.02


def test_geometry_resumes_and_refuses_bad_input(tiny_scene, tmp_path, capsys):
    out = tmp_path / "geo"
    assert _geometry(tiny_scene, out, "--set", "steps=10", "--set", "checkpoint_every_s=0") == 0
    assert _geometry(tiny_scene, out) == 2                       # exists, no --resume
    assert "already holds a geometry run" in capsys.readouterr().err
    assert main(["geometry", str(tiny_scene), "--out", str(out), "--resume", "--quiet"]) == 0
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    assert _geometry(tiny_scene, tmp_path / "g2", "--from-mesh", str(bad)) == 2
    err = capsys.readouterr().err
    assert "bad.ply" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "g2" / "sdf.pt").exists()


# --------------------------------------------------------------------------- nefii fit --geometry GEO


@pytest.fixture(scope="module")
def geo_folder(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("geo") / "geo"
    assert _geometry(tiny_scene, out, "--from-mesh", str(tiny_scene / "mesh.ply"), "--set", "steps=200",
                     "--set", "mesh_resolution=48") == 0
    return out


@pytest.mark.parametrize("mode", ["mesh", "sdf"])
def test_fit_and_eval_on_a_geometry_folder(tiny_scene, geo_folder, tmp_path, mode):
    from nefii.fit.config import resolve_config
    from nefii.fit.outputs import load_run
    run = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(run), "--preset", "tiny", "--quiet", "--geometry",
                 str(geo_folder), "--set", f"geometry_mode={mode}", "--set", "steps=10", "--set", "threads=1",
                 "--set", "material_offset_reconstructed=0.01"]) == 0
    # a reconstruction's material offset is material_offset_reconstructed (tiny's material_offset: 0.04)
    assert json.loads((run / "config.json").read_text())["material_offset"] == 0.01
    fitted = load_run(run)
    assert fitted.geometry.mode == mode and fitted.mesh == (geo_folder / "mesh.ply").resolve()
    feats = fitted.model.material.features
    assert (feats is not None) == (mode == "sdf")
    if mode == "sdf":
        # the fields see f: the material's first layer takes the hash-grid encoding plus f
        enc = fitted.model.material.encoding.out_dim
        assert fitted.model.material.net[0].in_features == enc + feats.dim
        # and the SDF inside model.pt is the geometry stage's, frozen
        sdf = load_sdf(geo_folder).sdf
        u = torch.rand(64, 3) - 0.5
        torch.testing.assert_close(feats.sdf(u)[1], sdf(u)[1])
        assert not any(p.requires_grad for p in feats.parameters())
    assert main(["eval", str(run), "--spp", "2", "--quiet"]) == 0
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert isinstance(metrics["masked"]["albedo_psnr"], float)
    if mode == "mesh":                            # the export bakes with the normals the fit used
        assert fitted.geometry.normal_sigma == resolve_config("tiny", []).normal_smoothing_reconstructed > 0
        assert main(["export", str(run), "--out", str(tmp_path / "asset" / "a.glb"), "--texture-size", "64",
                     "--quiet"]) == 0


def test_fit_geometry_input_errors(tiny_scene, geo_folder, tmp_path, capsys):
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "a"), "--preset", "tiny", "--quiet",
                 "--geometry", str(tmp_path), "--set", "steps=1"]) == 2
    assert "not a nefii geometry folder" in capsys.readouterr().err
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "b"), "--preset", "tiny", "--quiet",
                 "--set", "geometry_mode=sdf", "--set", "steps=1"]) == 2
    assert "needs --geometry" in capsys.readouterr().err
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "c"), "--preset", "tiny", "--quiet",
                 "--geometry", str(geo_folder), "--mesh", str(tiny_scene / "mesh.ply"), "--set", "steps=1"]) == 2
    assert "not both" in capsys.readouterr().err


# --------------------------------------------------------------------------- a built-in scene, real size (slow)


@pytest.mark.slow
@pytest.mark.parametrize("masks", ["on", "off"])
def test_geometry_reconstructs_the_bowl(tmp_path, masks):
    """``nefii geometry`` (cpu preset) on the bowl at 64x64, 32 views: the mesh within 2% (masks) or 5% (no
    masks) of the bounding-box diagonal in chamfer distance."""
    pytest.importorskip("mitsuba")
    data = tmp_path / "bowl"
    assert main(["synth", "bowl", "--out", str(data), "--res", "64", "--views", "32", "--test-views", "2",
                 "--spp", "16"]) == 0
    out = tmp_path / "geo"
    assert main(["geometry", str(data), "--out", str(out), "--masks", masks, "--quiet"]) == 0
    d = mesh_distance(trimesh.load(out / "mesh.ply", force="mesh"), trimesh.load(data / "mesh.ply", force="mesh"))
    assert d.chamfer_rel < (0.02 if masks == "on" else 0.05), d


def test_normal_prior_waits_for_its_start_step():
    """Before ``normal_smoothness_start * steps`` the objective is the one without the prior; from
    then on the prior adds to it."""
    cfg = resolve_geometry_config("tiny", ["normal_smoothness=10", "normal_smoothness_start=0.5", "area_weight=0"])
    gen = torch.Generator().manual_seed(0)
    pixels = 64
    d = torch.randn(pixels, 3, generator=gen)
    d = d / d.norm(dim=-1, keepdim=True)
    objective = ImageObjective(cfg, -2.0 * d, d, torch.rand(pixels, 3, generator=gen), torch.ones(pixels, dtype=torch.bool))
    plain = ImageObjective(dataclasses.replace(cfg, normal_smoothness=0.0), objective.origins, objective.directions,
                           objective.rgb, objective.mask)
    model = NeuSModel(cfg, background=False)

    def total(obj: ImageObjective, step: int) -> float:
        return float(obj.loss(model, step, torch.Generator().manual_seed(1)).total.detach())

    early, late = cfg.steps // 2 - 1, cfg.steps // 2
    assert total(objective, early) == total(plain, early)
    assert total(objective, late) > total(plain, late) + 1e-3


def test_per_view_gains_multiply_each_views_rendered_colour(monkeypatch):
    """With ``exposure = per_view`` the colour each ray renders is multiplied by its own view's gain (pixel ``i``
    is view ``i // view_pixels``) before it meets the photo, and the gains are the model's parameters (the
    optimiser trains them) with their prior in the total."""
    import nefii.sdf.train as train
    cfg = resolve_geometry_config("tiny", ["area_weight=0", "normal_smoothness=0", "exposure=per_view"])
    gen = torch.Generator().manual_seed(0)
    per_view = 32
    d = torch.randn(2 * per_view, 3, generator=gen)
    d = d / d.norm(dim=-1, keepdim=True)
    obj = ImageObjective(cfg, -2.0 * d, d, torch.rand(2 * per_view, 3, generator=gen), None, view_pixels=per_view)
    model = NeuSModel(cfg, background=False, num_views=2)
    assert any(p is model.gains.log_gain for p in model.parameters())
    seen: list = []
    real_draw, real_loss = train.draw_rays, train.geometry_loss
    monkeypatch.setattr(train, "draw_rays", lambda *a: seen.append(real_draw(*a)) or seen[-1])
    monkeypatch.setattr(train, "geometry_loss", lambda out, *a: seen.append(out.rgb.detach()) or real_loss(out, *a))

    def rendered(log_gain: list[float]) -> tuple[torch.Tensor, torch.Tensor, float]:
        with torch.no_grad():
            model.gains.log_gain.copy_(torch.tensor(log_gain)[:, None].expand(2, 3))
        seen.clear()
        total = float(obj.loss(model, 0, torch.Generator().manual_seed(1)).total.detach())
        return seen[0][0], seen[1], total

    i, plain, total_plain = rendered([0.0, 0.0])
    j, gained, total_gained = rendered([-0.3, 0.5])             # centred: gains exp(-0.4) and exp(+0.4)
    assert torch.equal(i, j) and len(torch.unique(i // per_view)) == 2
    expected = torch.exp(torch.where(i // per_view == 0, -0.4, 0.4))[:, None]
    torch.testing.assert_close(gained, plain * expected, rtol=1e-5, atol=1e-7)
    assert total_gained != total_plain


def test_an_appearance_encoding_gives_the_colour_a_table_of_its_own():
    """With ``appearance_encoding`` the colour network reads the point through an encoding that the SDF
    does not use: changing that table changes the colour and leaves the surface where it was; without
    it the colour has no encoding. ``view_freqs`` sets the view direction's Fourier features."""
    plain = NeuSModel(resolve_geometry_config("tiny", []), background=False)
    assert plain.color.encoding is None
    cfg = resolve_geometry_config("tiny", ["appearance_encoding=true", "view_freqs=0"])
    model = NeuSModel(cfg, background=False)
    assert model.color.dir_enc.out_dim == 3 and isinstance(model.color.encoding, HashGrid)
    assert model.color.encoding is not model.sdf.encoding
    u = uniform_in_ball(256, torch.Generator().manual_seed(0), torch.device("cpu"))
    n = torch.nn.functional.normalize(u, dim=-1)
    with torch.no_grad():
        sdf0, feat = model.sdf(u)
        rgb0 = model.color(u, n, -n, feat)
        for p in model.color.encoding.parameters():
            p.add_(torch.randn_like(p))
        rgb1 = model.color(u, n, -n, model.sdf(u)[1])
        sdf1 = model.sdf(u)[0]
    assert torch.equal(sdf0, sdf1)
    assert float((rgb1 - rgb0).abs().max()) > 1e-3


def test_a_reconstruction_takes_its_own_material_offset_and_normal_smoothing(tmp_path):
    from nefii.fit.config import resolve_config
    from nefii.fit.geometry_source import GeometrySource, adapt_to_source
    cfg = resolve_config("cpu", ["material_offset_reconstructed=0.005", "normal_smoothing_reconstructed=0.01",
                                 "lookup_smoothing_reconstructed=0.03"])
    mesh = GeometrySource("mesh", tmp_path / "mesh.ply")
    recon = GeometrySource("mesh", tmp_path / "geo" / "mesh.ply", tmp_path / "geo")
    assert adapt_to_source(cfg, mesh) == (cfg, mesh) and cfg.material_offset == 0.04
    cfg_r, recon_r = adapt_to_source(cfg, recon)
    assert cfg_r.material_offset == 0.005 and recon_r.normal_sigma == 0.01 and recon_r.lookup_sigma == 0.03
    assert adapt_to_source(cfg_r, recon_r) == (cfg_r, recon_r)                 # a resumed run: the same
    assert GeometrySource.from_dict(recon_r.to_dict()) == recon_r
    sdf_mode = GeometrySource("sdf", tmp_path / "geo" / "mesh.ply", tmp_path / "geo")
    sdf_r = adapt_to_source(cfg, sdf_mode)[1]
    assert sdf_r.normal_sigma == sdf_r.lookup_sigma == 0.0                   # the SDF's gradient is its normal


def test_smoothed_vertex_normals_lose_noise_and_keep_the_faces_of_a_thin_wall_apart():
    from nefii.raycast.mesh import smooth_vertex_normals
    sphere = trimesh.creation.icosphere(subdivisions=4)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    rng = np.random.default_rng(0)
    noisy = v + 0.15 * rng.normal(size=v.shape)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    err = lambda n: np.degrees(np.arccos(np.clip((n * v).sum(-1), -1, 1))).mean()  # noqa: E731
    smooth = smooth_vertex_normals(v, f, noisy, 0.1)
    assert err(smooth) < 0.5 * err(noisy)
    assert np.allclose(np.linalg.norm(smooth, axis=-1), 1.0, atol=1e-6)
    assert smooth_vertex_normals(v, f, noisy, 0.0) is noisy
    # a plate 1% thick: its top and bottom meet only along the rim, so the centres keep +z and -z
    plate = trimesh.creation.box(extents=(2.0, 2.0, 0.02)).subdivide().subdivide().subdivide()
    pv, pf = np.asarray(plate.vertices), np.asarray(plate.faces)
    pn = np.asarray(plate.vertex_normals)
    out = smooth_vertex_normals(pv, pf, pn, 0.05)
    centre = np.linalg.norm(pv[:, :2], axis=-1) < 0.5
    assert np.all(out[centre, 2] * np.sign(pv[centre, 2]) > 0.99)
