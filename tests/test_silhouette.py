"""Pixels the silhouette crosses: where the background shows, their colour mixes object and background,
so the fit leaves them out of both."""
from __future__ import annotations

import dataclasses

import torch

from fit_fixtures import scene_mesh, write_rendered_scene
from nefii.camera import jittered_pixel_rays
from nefii.data import load_scene
from nefii.fit.pixels import first_hits
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


def test_pixels_the_silhouette_crosses_are_left_out_where_the_background_shows(tmp_path):
    rgba = load_scene(write_rendered_scene(tmp_path / "s", res=24, n_train=2, n_test=1))
    photo = dataclasses.replace(rgba, masks=None, background_visible=True)  # as a photo: no masks, a background
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    cover = torch.cat([_coverage(photo, geometry, v) for v in range(len(photo))])
    kept, transparent = first_hits(photo, geometry), first_hits(rgba, geometry)
    obj_cover = cover[_pixel_index(photo, geometry, kept)]
    assert obj_cover.min() >= 0.85  # no object pixel is much background
    # the RGBA render's object pixels (centre ray on the object) include pixels half background
    assert cover[_pixel_index(rgba, geometry, transparent)].min() < 0.6
    assert len(kept.points) < len(transparent.points)
    bg_dirs = kept.bg_dirs
    # every background pixel's direction is a view ray that misses near all its corners: none is covered
    flat_d = torch.cat([_dirs(photo, v) for v in range(len(photo))])
    idx = _match(flat_d, bg_dirs)
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
