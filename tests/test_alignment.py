"""The given mesh against the masks (:mod:`nefii.fit.alignment`): agreement measured away from the masks' edges,
a mesh in another frame refused with the turn that aligns it, inverted masks named as such."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fit_fixtures import write_rendered_scene

from nefii.data import load_scene
from nefii.errors import InputError
from nefii.fit.alignment import AGREEMENT, check_alignment, mask_agreement
from nefii.raycast import MeshGeometry


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = write_rendered_scene(tmp_path_factory.mktemp("scene") / "s", res=24, n_train=4, n_test=1)
    return load_scene(root, "train"), MeshGeometry.from_file(root / "mesh.ply", threads=1)


def test_the_scene_own_mesh_agrees_and_a_shifted_one_less(scene):
    data, mesh = scene
    own = mask_agreement(data, mesh)
    assert own.iou == 1.0 and own.inside > 100
    shifted = MeshGeometry(mesh.vertices + np.float32([0.25, 0.0, 0.0]), mesh.faces, threads=1)
    assert AGREEMENT[1] < mask_agreement(data, shifted).iou < AGREEMENT[0]
    assert check_alignment(data, mesh, data.root / "mesh.ply").iou == 1.0
    with pytest.warns(UserWarning, match="is the mesh aligned with the cameras"):
        check_alignment(data, shifted, data.root / "shifted.ply")


def test_a_mesh_turned_about_x_is_refused_with_the_turn_back(scene):
    data, mesh = scene
    x, y, z = mesh.vertices.T
    y_up = MeshGeometry(np.stack([x, z, -y], -1), mesh.faces, threads=1)
    assert mask_agreement(data, y_up).iou < AGREEMENT[1]
    with pytest.raises(InputError, match=r"turned \+90 degrees about x they agree on 100.0%"):
        check_alignment(data, y_up, data.root / "y_up.glb")


def test_inverted_masks_are_named_not_the_mesh(scene):
    data, mesh = scene
    inverted = dataclasses.replace(data, masks=~data.masks)
    with pytest.raises(InputError, match="with the masks inverted: are the masks white on the background") as e:
        check_alignment(inverted, mesh, data.root / "mesh.ply")
    assert str(data.root) in str(e.value)


def test_no_masks_no_check(scene):
    data, mesh = scene
    assert check_alignment(dataclasses.replace(data, masks=None), mesh, data.root / "mesh.ply") is None
