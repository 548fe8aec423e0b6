"""The fit's pixels as footprints: hits at a 2 x 2 grid inside each pixel, the sky past the silhouette, and the
two-point pair estimate."""
from __future__ import annotations

import dataclasses

import pytest
import torch

import nefii.fit.pixels as pixels
from fit_fixtures import scene_mesh, write_rendered_scene
from nefii.data import load_scene
from nefii.errors import InputError
from nefii.fit.losses import observed_loss
from nefii.fit.path_trace import PathTraced, SurfacePoints, environment_where, two_point_pair
from nefii.fit.pixels import FOOTPRINT_GRID, first_hits
from nefii.raycast import MeshGeometry, Rays
from nefii.render.estimator import RadianceEstimate


def _pixel_coordinates(x: torch.Tensor, c2w: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Continuous pixel coordinates (OpenCV: pixel ``(j, i)`` spans ``[j, j + 1) x [i, i + 1)``) of world points."""
    w2c = torch.linalg.inv(c2w.double())
    p = x.double() @ w2c[:3, :3].T + w2c[:3, 3]
    return torch.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], -1)


def test_footprint_hits_sit_at_the_grid_inside_their_pixel(tmp_path):
    scene = load_scene(write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1))
    mesh = scene_mesh()
    px = first_hits(scene, MeshGeometry(mesh.vertices, mesh.faces))
    P, F = len(px.points), len(FOOTPRINT_GRID)
    assert len(px.footprint) == F * P
    c2w, K = scene.cameras.c2w[0], scene.cameras.K[0].double()
    mine = (px.view == 0).nonzero()[:, 0]
    centre = _pixel_coordinates(px.points.position[mine], c2w, K)
    base = torch.floor(centre)                        # the pixel each object pixel's centre ray went through
    torch.testing.assert_close(centre - base, torch.full_like(centre, 0.5), atol=1e-3, rtol=0)
    moved = 0
    for k, u in enumerate(FOOTPRINT_GRID):
        at = px.footprint[k * P + mine]
        xy = _pixel_coordinates(at.position, c2w, K)
        on_grid = ((xy - base - torch.tensor(u, dtype=xy.dtype)).abs() < 1e-3).all(-1)
        is_centre = (at.position == px.points.position[mine]).all(-1)
        assert bool((on_grid | is_centre).all())      # at the grid position, or the centre where that ray missed
        moved += int(on_grid.sum())
        # the view direction is the ray's own
        torch.testing.assert_close(at.wo.norm(dim=-1), torch.ones(len(mine)), atol=1e-5, rtol=0)
    assert moved > 0.9 * F * len(mine)


def test_select_and_at_footprint_index_the_same_pixels(tmp_path):
    scene = load_scene(write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1))
    mesh = scene_mesh()
    px = first_hits(scene, MeshGeometry(mesh.vertices, mesh.faces))
    P = len(px.points)
    idx = torch.tensor([P - 1, 0, P // 2, 0])
    batch = px.select(idx, torch.zeros(0, dtype=torch.long))
    k = torch.tensor([3, 0, 2, 1])
    want, want_sky = px.footprint[k * P + idx], px.footprint_sky[k * P + idx]
    got, sky = batch.at_footprint(k)
    torch.testing.assert_close(got.position, want.position, rtol=0, atol=0)
    torch.testing.assert_close(got.normal, want.normal, rtol=0, atol=0)
    assert torch.equal(sky, want_sky) and torch.equal(batch.edge, px.edge[idx])


def test_a_transparent_render_has_no_edge_pixels_and_a_photo_sees_the_sky_past_its_silhouette(tmp_path):
    rgba = load_scene(write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1))
    photo = dataclasses.replace(rgba, masks=None, background_visible=True)
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    transparent, px = first_hits(rgba, geometry), first_hits(photo, geometry)
    assert not bool(transparent.edge.any()) and not bool(transparent.footprint_sky.any())
    P, F = len(px.points), len(FOOTPRINT_GRID)
    sky = px.footprint_sky.reshape(F, P)
    assert bool(px.edge.any()) and bool(sky.any())
    assert not bool(sky[:, ~px.edge].any())            # only edge pixels see past the object
    rows = px.footprint_sky.nonzero()[:, 0]
    at = px.footprint[rows]
    torch.testing.assert_close(at.position, px.points.position[rows % P], rtol=0, atol=0)  # the centre stands in
    for v in range(len(photo)):                        # each sky row's ray, from its camera along -wo, misses
        mine = rows[px.view[rows % P] == v]
        d = -px.footprint.wo[mine]
        o = photo.cameras.c2w[v][:3, 3].float().expand(len(d), 3)
        assert not bool(geometry.intersect(Rays(o.contiguous(), d.contiguous())).valid.any())
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d)), atol=1e-5, rtol=0)


def test_environment_where_replaces_the_sky_rows_and_their_gradient_only():
    g = torch.Generator().manual_seed(0)
    diffuse = torch.rand(6, 3, generator=g, requires_grad=True)
    specular = torch.rand(6, 3, generator=g, requires_grad=True)
    sky_light = torch.rand(6, 3, generator=g, requires_grad=True)
    sky = torch.tensor([False, True, False, False, True, False])
    pts = SurfacePoints(*(torch.rand(4, 3, generator=g) for _ in range(5)))
    est = RadianceEstimate(diffuse, specular)
    out = environment_where(PathTraced(est, (est, est), pts), sky, sky_light)
    for e in (out.radiance, *out.pair):
        torch.testing.assert_close(e.rgb[sky], sky_light[sky].detach())
        torch.testing.assert_close(e.rgb[~sky], (diffuse + specular)[~sky].detach())
    out.radiance.rgb.sum().backward()
    assert bool((diffuse.grad[sky] == 0).all()) and bool((diffuse.grad[~sky] == 1).all())
    assert bool((sky_light.grad[~sky] == 0).all()) and bool((sky_light.grad[sky] == 1).all())
    assert out.secondary is pts


def test_the_cache_term_reads_only_its_rows():
    g = torch.Generator().manual_seed(1)
    B = 8
    traced = PathTraced(RadianceEstimate(torch.rand(B, 3, generator=g), torch.zeros(B, 3)), None,
                        SurfacePoints(*(torch.rand(1, 3, generator=g) for _ in range(5))))
    cache, target = torch.rand(B, 3, generator=g), torch.rand(B, 3, generator=g)
    rows = torch.tensor([True, False, True, True, False, True, True, False])
    none = torch.zeros(0, 3)
    mine = observed_loss(traced, cache, target, none, none, "log1p", "l2", cache_rows=rows)
    alone = observed_loss(PathTraced(RadianceEstimate(traced.radiance.diffuse[rows], torch.zeros(int(rows.sum()), 3)), None,
                                     traced.secondary), cache[rows], target[rows], none, none, "log1p", "l2")
    torch.testing.assert_close(mine.cache, alone.cache)
    moved = cache.clone()
    moved[~rows] += 5.0
    torch.testing.assert_close(observed_loss(traced, moved, target, none, none, "log1p", "l2",
                                             cache_rows=rows).cache, mine.cache)
    everything = observed_loss(traced, cache, target, none, none, "log1p", "l2")
    assert float((everything.cache - mine.cache).abs()) > 1e-4


def test_two_point_pair_splits_halves_and_averages():
    B = 5
    g = torch.Generator().manual_seed(0)
    diffuse, specular = torch.rand(2 * B, 3, generator=g), torch.rand(2 * B, 3, generator=g)
    pts = SurfacePoints(*(torch.rand(7, 3, generator=g) for _ in range(5)))
    traced = PathTraced(RadianceEstimate(diffuse, specular), None, pts)
    out = two_point_pair(traced, B)
    a, b = out.pair
    torch.testing.assert_close(a.rgb, diffuse[:B] + specular[:B])
    torch.testing.assert_close(b.rgb, diffuse[B:] + specular[B:])
    torch.testing.assert_close(out.radiance.rgb, 0.5 * (a.rgb + b.rgb))
    assert out.secondary is pts


def test_first_hits_that_would_not_fit_in_memory_are_refused_with_the_data_named(tmp_path, monkeypatch):
    root = write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1)
    scene, mesh = load_scene(root), scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    P = len(first_hits(scene, geometry).points)
    per_point = 4 * 3 * 5                            # five float32 vectors a surface point
    monkeypatch.setattr(pixels, "host_memory_bytes", lambda: (len(FOOTPRINT_GRID) + 2) * P * per_point - 1)
    with pytest.raises(InputError, match=f"first hits of {P} object pixels .* max_image_side") as err:
        first_hits(scene, geometry)
    assert str(root.name) in str(err.value)
    monkeypatch.setattr(pixels, "host_memory_bytes", lambda: (len(FOOTPRINT_GRID) + 2) * P * per_point)
    assert len(first_hits(scene, geometry).points) == P
