"""Clipped 8-bit pixels: found when the images are read, left out of the fit's photometric loss."""
from __future__ import annotations

import dataclasses

import torch

from data_fixtures import make_truth, write_nefii, write_physg
from fit_fixtures import scene_mesh, write_rendered_scene
from nefii.data import load_scene
from nefii.fit.pixels import first_hits, view_rays
from nefii.raycast import MeshGeometry, Rays


def test_load_scene_reports_pixels_at_the_top_code(tmp_path):
    t = make_truth()
    want = (t.srgb8 >= 254).any(-1)
    assert want.any() and not want.all()  # random codes: some clip, most do not
    write_physg(tmp_path / "png", t)
    scene = load_scene(tmp_path / "png")
    assert torch.equal(scene.clipped, torch.from_numpy(want))


def test_exr_scenes_have_no_clipped_pixels(tmp_path):
    write_nefii(tmp_path / "exr", make_truth(), png=False)
    assert load_scene(tmp_path / "exr").clipped is None


def test_first_hits_leave_clipped_pixels_out(tmp_path):
    scene = load_scene(write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1))
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    obj = []
    for v in range(len(scene)):
        o, d = view_rays(scene, v)
        obj.append(geometry.intersect(Rays(o.reshape(-1, 3), d.reshape(-1, 3))).valid.reshape(o.shape[:2]))
    obj = torch.stack(obj) & scene.masks
    clipped = torch.rand(scene.images.shape[:3], generator=torch.Generator().manual_seed(0)) < 0.3
    assert (obj & clipped).any() and (obj & ~clipped).any()
    part = first_hits(dataclasses.replace(scene, clipped=clipped), geometry)
    assert torch.equal(part.rgb, scene.images[obj & ~clipped])  # the unclipped object pixels, in order
    assert len(first_hits(scene, geometry).rgb) == int(obj.sum())
