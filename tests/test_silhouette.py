"""Pixels the silhouette crosses: where the background shows, their colour mixes object and background, so
the fit renders them as that mixture: the footprint positions past the silhouette see the environment."""
from __future__ import annotations

import dataclasses

import torch

from fit_fixtures import scene_mesh, write_rendered_scene
from nefii.camera import jittered_pixel_rays
from nefii.data import load_scene
from nefii.fit.pixels import FOOTPRINT_GRID, first_hits
from nefii.raycast import MeshGeometry, Rays


def _coverage(scene, geometry, v: int, n: int = 8) -> torch.Tensor:
    """The share of each pixel of view ``v`` that the geometry covers, from ``n x n`` stratified rays."""
    pixel = torch.arange(scene.height * scene.width)
    hits = torch.zeros(len(pixel))
    for a in range(n):
        for b in range(n):
            u = torch.tensor([(a + 0.5) / n, (b + 0.5) / n], dtype=torch.float64).expand(len(pixel), 2)
            o, d = jittered_pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], scene.width, pixel, u)
            hits += geometry.intersect(Rays(o.float(), d.float())).valid.float()
    return hits / n**2


def test_pixels_the_silhouette_crosses_are_fitted_as_object_and_sky_where_the_background_shows(tmp_path):
    rgba = load_scene(write_rendered_scene(tmp_path / "s", res=24, n_train=2, n_test=1))
    photo = dataclasses.replace(rgba, masks=None, background_visible=True)  # as a photo: no masks, a background
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    cover = torch.cat([_coverage(photo, geometry, v) for v in range(len(photo))])
    px = first_hits(photo, geometry)
    obj_cover = cover[_pixel_index(photo, geometry, px)]
    assert obj_cover[~px.edge].min() >= 0.85           # a pixel fitted as object alone is hardly background
    assert int(px.edge.sum()) > 20 and obj_cover[px.edge].min() < 0.6
    # an edge pixel's footprint sees the sky in about the share of the pixel the object leaves uncovered
    P = len(px.points)
    sky_share = px.footprint_sky.reshape(len(FOOTPRINT_GRID), P).float().mean(0)
    err = sky_share[px.edge] - (1 - obj_cover[px.edge])
    assert float(err.abs().mean()) <= 0.15 and abs(float(err.mean())) <= 0.08
    # every background pixel's direction is a view ray that misses near all its corners: none is covered
    flat_d = torch.cat([_dirs(photo, v) for v in range(len(photo))])
    idx = _match(flat_d, px.bg_dirs)
    assert cover[idx].max() <= 0.15


def _dirs(scene, v: int) -> torch.Tensor:
    from nefii.fit.pixels import view_rays

    return view_rays(scene, v)[1].reshape(-1, 3)


def _match(all_dirs: torch.Tensor, some: torch.Tensor) -> torch.Tensor:
    """Indices into ``all_dirs`` of the rows of ``some`` (view directions are distinct within a scene)."""
    return torch.cdist(some.double(), all_dirs.double()).argmin(1)


def _pixel_index(scene, geometry, px) -> torch.Tensor:
    """Flat (view, pixel) indices of the object pixels of ``px``, found by their view ray."""
    all_d = torch.cat([_dirs(scene, v) for v in range(len(scene))])
    return _match(all_d, -px.points.wo)
