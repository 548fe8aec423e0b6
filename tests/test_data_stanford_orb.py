"""Stanford-ORB's blender layout read as it ships (tests/orb_fixtures.py writes it): detection, splits,
cameras, masks, the novel-light photographs with their maps turned into the world, and bad input."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from data_fixtures import H, W, make_truth, save_png
from nefii.data import detect_format, load_scene
from nefii.data.stanford_orb import camera_uv
from nefii.errors import InputError
from nefii.io.exr import write_exr
from nefii.render.equirect import pixel_directions
from orb_fixtures import ENV_H, ENV_W, OTHERS, SCENE, TRIANGLE_OBJ, lobe_light, write_orb

TRAIN, TEST = make_truth(4, seed=0, centred=True), make_truth(2, seed=1, centred=True)
NOVEL = {OTHERS[0]: make_truth(2, seed=2, centred=True), OTHERS[1]: make_truth(3, seed=3, centred=True)}
LIGHTS = {SCENE: lobe_light((0.0, 0.0, 1.0)), OTHERS[0]: lobe_light((0.3, -0.5, 0.8), (3.0, 2.0, 1.0)),
          OTHERS[1]: lobe_light((-0.7, 0.6, 0.2), (1.0, 2.0, 4.0))}


def orb(tmp_path, **kw):
    return write_orb(tmp_path / "data", TRAIN, TEST, NOVEL, LIGHTS, mesh=TRIANGLE_OBJ, **kw)


def load_error(*args, **kwargs) -> InputError:
    with pytest.raises(InputError) as info:
        load_scene(*args, **kwargs)
    assert "\n" not in str(info.value) and info.value.exit_code == 2
    return info.value


def assert_views(images, masks, cameras, truth):
    assert torch.allclose(images, torch.from_numpy(truth.images), atol=1e-6)
    assert torch.equal(masks, torch.from_numpy(truth.masks))
    assert torch.allclose(cameras.K, torch.from_numpy(truth.K).expand(truth.n, 3, 3), atol=1e-9)
    assert torch.allclose(cameras.c2w, torch.from_numpy(truth.c2w), atol=1e-9)
    assert (cameras.height, cameras.width) == (H, W)


def test_detected_and_both_splits_read(tmp_path):
    root = orb(tmp_path)
    for split in ("train", "test"):
        fmt, folder = detect_format(root, split)
        assert fmt.name == "stanford_orb" and folder == root
    train = load_scene(root, "train")
    assert train.format == "stanford_orb" and train.relit == () and train.background_visible
    assert_views(train.images, train.masks, train.cameras, TRAIN)
    assert train.names == ("train/0000.exr", "train/0001.exr", "train/0002.exr", "train/0003.exr")
    assert train.indices == (0, 1, 2, 3)
    assert train.mesh_path == (tmp_path / "data" / "ground_truth" / SCENE / "mesh_blender" / "mesh.obj").resolve()
    assert train.envmap is None and train.ground_truth is None
    test = load_scene(root, "test")
    assert_views(test.images, test.masks, test.cameras, TEST)
    assert test.indices == (10, 11)


def test_novel_light_photographs_are_relit_sets_with_their_own_cameras(tmp_path):
    test = load_scene(orb(tmp_path), "test")
    assert [r.name for r in test.relit] == list(OTHERS)
    for r, (name, truth), first in zip(test.relit, NOVEL.items(), (20, 30)):
        assert r.name == name and len(r) == truth.n
        assert_views(r.images, r.masks, r.cameras, truth)
        assert r.indices == tuple(range(first, first + truth.n))
        assert r.envmap is None and r.view_envmaps.shape == (truth.n, ENV_H, ENV_W, 3)
    moved = test.to("meta")
    assert moved.relit[0].cameras.c2w.device.type == "meta" and moved.relit[0].view_envmaps.device.type == "meta"


def test_camera_frame_maps_become_the_world_light(tmp_path):
    """Each photograph's map, stored in its camera's frame on Stanford-ORB's grid, read back as the one world
    light in nefii's mapping (a smooth lobe: bilinear lookups agree to a few percent), whichever camera."""
    test = load_scene(orb(tmp_path), "test")
    d = pixel_directions(ENV_H, ENV_W, dtype=torch.float64).numpy()
    for r in test.relit:
        axis = np.asarray({OTHERS[0]: (0.3, -0.5, 0.8), OTHERS[1]: (-0.7, 0.6, 0.2)}[r.name])
        want = LIGHTS[r.name](d)
        for v in range(len(r)):
            got = r.view_envmaps[v].numpy()
            assert np.abs(got - want).max() < 0.03 * want.max(), (r.name, v)   # measured < 0.01
            brightest = d.reshape(-1, 3)[got.sum(-1).argmax()]
            assert brightest @ axis / np.linalg.norm(axis) > np.cos(np.radians(8.0))


def test_camera_uv_of_known_directions():
    """OpenCV camera axes: forward at the centre, right at u = 0.75, left at 0.25, up on row 0, behind on the seam."""
    d = np.array([[0, 0, 1.0], [1, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1]])
    u, v = camera_uv(d)
    assert np.allclose(u[[0, 1, 2]], [0.5, 0.75, 0.25]) and np.allclose(v[[0, 1, 2, 5]], 0.5)
    assert np.allclose(v[[3, 4]], [0.0, 1.0]) and np.isclose(u[5] % 1.0, 0.0)


def test_ldr_variant_and_angle_at_the_top_level(tmp_path):
    root = orb(tmp_path, hdr=False, novel_angle_top_level=True)
    assert root.parent.name == "blender_LDR"
    test = load_scene(root, "test")
    assert test.names == ("test/0010.png", "test/0011.png")
    assert_views(test.images, test.masks, test.cameras, TEST)
    assert [len(r) for r in test.relit] == [2, 3]
    assert_views(test.relit[1].images, test.relit[1].masks, test.relit[1].cameras, NOVEL[OTHERS[1]])


def test_without_transforms_novel_there_is_nothing_to_relight(tmp_path):
    root = orb(tmp_path)
    (root / "transforms_novel.json").unlink()
    assert load_scene(root, "test").relit == ()


def test_without_the_ground_truth_folder_the_novel_views_are_left_out_with_a_warning(tmp_path):
    """(It is a download of its own; eval of the test views must not need it.)"""
    root = orb(tmp_path)
    shutil.rmtree(tmp_path / "data" / "ground_truth")
    with pytest.warns(UserWarning, match="ground_truth"):
        test = load_scene(root, "test")
    assert test.relit == () and test.mesh_path is None and len(test) == TEST.n


# ---------------------------------------------------------------------------- bad input

def _edit_novel(root, edit):
    path = root / "transforms_novel.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize("frame, key", [(1, "scene_name"), (3, "transform_matrix"), (2, "camera_angle_x")])
def test_novel_frame_without_a_field(tmp_path, frame, key):
    root = orb(tmp_path)
    path = _edit_novel(root, lambda m: m["frames"][frame].pop(key))
    e = load_error(root, "test")
    assert e.path == str(path) and f"frame {frame}" in e.problem and key in e.problem


def test_novel_capture_folder_missing(tmp_path):
    root = orb(tmp_path)
    _edit_novel(root, lambda m: m["frames"][0].update(scene_name="toy_scene009"))
    e = load_error(root, "test")
    assert e.path.endswith("toy_scene009") and "scene_name" in e.problem


def test_novel_photograph_missing(tmp_path):
    root = orb(tmp_path)
    (root.parent / OTHERS[1] / "test" / "0031.exr").unlink()
    e = load_error(root, "test")
    assert e.path == str(root.parent.resolve() / OTHERS[1] / "test" / "0031") and "not found" in e.problem


def test_novel_environment_map_missing(tmp_path):
    root = orb(tmp_path)
    env = tmp_path / "data" / "ground_truth" / OTHERS[0] / "env_map" / "0021.exr"
    env.unlink()
    e = load_error(root, "test")
    assert e.path == str(env.resolve()) and "environment map not found" in e.problem
    assert load_scene(root, "train").relit == ()          # the training split does not need it


def test_novel_environment_maps_of_different_sizes(tmp_path):
    root = orb(tmp_path)
    env = tmp_path / "data" / "ground_truth" / OTHERS[1] / "env_map" / "0032.exr"
    write_exr(env, np.ones((8, 16, 3), np.float32))
    e = load_error(root, "test")
    assert e.path == str(env.resolve()) and "16x8" in e.problem


def test_black_environment_map(tmp_path):
    root = orb(tmp_path)
    env = tmp_path / "data" / "ground_truth" / OTHERS[0] / "env_map" / "0020.exr"
    write_exr(env, np.zeros((ENV_H, ENV_W, 3), np.float32))
    e = load_error(root, "test")
    assert e.path == str(env.resolve()) and "black" in e.problem


@pytest.mark.parametrize("where", ["train", "novel"])
def test_mask_of_the_wrong_size(tmp_path, where):
    root = orb(tmp_path)
    mask = (root / "train_mask" / "0002.png" if where == "train"
            else root.parent / OTHERS[0] / "test_mask" / "0021.png")
    save_png(mask, np.full((H + 1, W, 3), 255, np.uint8))
    e = load_error(root, "train" if where == "train" else "test")
    assert e.path.endswith(str(mask.relative_to(root.parent))) and f"{W}x{H + 1}" in e.problem


def test_mask_missing(tmp_path):
    root = orb(tmp_path)
    (root / "test_mask" / "0011.png").unlink()
    e = load_error(root, "test")
    assert e.path == str(root / "test_mask" / "0011.png") and "not found" in e.problem
