"""Bad input: each problem is one InputError line naming the file and the problem (exit code 2)."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from PIL import Image

from data_fixtures import (H, W, make_truth, mask8, premultiplied, write_colmap, write_nefii, write_neus,
                           write_physg)
from nefii.data import load_scene
from nefii.data.validate import check_c2w
from nefii.errors import InputError
from nefii.io.exr import write_exr

TRUTH = make_truth()


def load_error(*args, **kwargs) -> InputError:
    """The InputError ``load_scene`` raises; checks it is one line with exit code 2."""
    with pytest.raises(InputError) as info:
        load_scene(*args, **kwargs)
    e = info.value
    assert "\n" not in str(e) and e.exit_code == 2
    return e


def nefii_scene(tmp_path, **kw):
    write_nefii(tmp_path, TRUTH, extras=False, **kw)
    return tmp_path


# ---------------------------------------------------------------------------- files

def test_missing_image(tmp_path):
    root = nefii_scene(tmp_path)
    for f in root.glob("train/r_2.*"):
        f.unlink()
    e = load_error(root)
    assert "r_2" in e.path and "not found" in e.problem


def test_unreadable_png(tmp_path):
    root = nefii_scene(tmp_path, exr=False)
    (root / "train/r_1.png").write_bytes(b"not a png at all")
    e = load_error(root)
    assert e.path.endswith("r_1.png") and "not a readable image" in e.problem


def test_unreadable_exr(tmp_path):
    root = nefii_scene(tmp_path)
    (root / "train/r_1.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    e = load_error(root)
    assert e.path.endswith("r_1.exr") and "OpenEXR" in e.problem


def test_images_of_different_sizes(tmp_path):
    root = nefii_scene(tmp_path, exr=False)
    Image.new("RGBA", (W + 1, H)).save(root / "train/r_2.png")
    e = load_error(root)
    assert e.path.endswith("r_2.png") and f"{W + 1}x{H}" in e.problem and "same size" in e.problem


def test_json_size_disagrees_with_images(tmp_path):
    root = nefii_scene(tmp_path)
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["w"] = 16
    (root / "transforms_train.json").write_text(json.dumps(meta))
    e = load_error(root)
    assert e.path.endswith("r_0.exr") and "w=16" in e.problem


@pytest.mark.parametrize("bad", [np.nan, np.inf], ids=["nan", "inf"])
def test_non_finite_pixels(tmp_path, bad):
    root = nefii_scene(tmp_path)
    img = premultiplied(TRUTH, 3)
    img[2, 3, 1] = bad
    write_exr(root / "train/r_3.exr", img)
    e = load_error(root)
    assert e.path.endswith("r_3.exr") and "NaN or infinite" in e.problem


def test_non_finite_envmap(tmp_path):
    root = nefii_scene(tmp_path)
    write_exr(root / "envmap.exr", np.full((4, 8, 3), np.inf, np.float32))
    e = load_error(root)
    assert e.path.endswith("envmap.exr") and "NaN or infinite" in e.problem


def test_empty_alpha_mask(tmp_path):
    root = nefii_scene(tmp_path, exr=False)
    rgba = np.zeros((H, W, 4), np.uint8)
    Image.fromarray(rgba).save(root / "train/r_1.png")
    e = load_error(root)
    assert e.path.endswith("r_1.png") and "mask is empty" in e.problem


def test_empty_mask_file(tmp_path):
    write_neus(tmp_path, TRUTH)
    Image.fromarray(np.zeros((H, W), np.uint8)).save(tmp_path / "mask/002.png")
    e = load_error(tmp_path)
    assert e.path.endswith("mask/002.png") and "mask is empty" in e.problem


def test_mask_missing_for_one_view(tmp_path):
    write_physg(tmp_path, TRUTH)
    (tmp_path / "mask/001.png").unlink()
    e = load_error(tmp_path)
    assert "mask/001.png" in e.path and "not found" in e.problem


# ---------------------------------------------------------------------------- poses

def test_singular_pose(tmp_path):
    root = nefii_scene(tmp_path)
    path = root / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][2]["transform_matrix"] = [[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]
    path.write_text(json.dumps(meta))
    e = load_error(root)
    assert e.path.endswith("transforms_train.json") and "frame 2" in e.problem and "singular" in e.problem


def test_non_rotation_pose(tmp_path):
    root = nefii_scene(tmp_path)
    path = root / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][1]["transform_matrix"] = (np.diag([2.0, 1.0, 1.0, 1.0])).tolist()
    path.write_text(json.dumps(meta))
    e = load_error(root)
    assert "frame 1" in e.problem and "orthonormal" in e.problem


def test_check_c2w_helper():
    with pytest.raises(InputError, match=r"cams.json: view 7: camera rotation is a reflection"):
        check_c2w(np.diag([1.0, 1.0, -1.0, 1.0]), "cams.json", "view 7")
    assert check_c2w(np.eye(4)[:3], "cams.json", "view 0").shape == (4, 4)


def test_singular_world_mat(tmp_path):
    write_neus(tmp_path, TRUTH)
    arrays = dict(np.load(tmp_path / "cameras_sphere.npz"))
    arrays["world_mat_1"][:, 2] = 0.0
    np.savez(tmp_path / "cameras_sphere.npz", **arrays)
    e = load_error(tmp_path)
    assert e.path.endswith("cameras_sphere.npz") and "world_mat_1" in e.problem and "singular" in e.problem


def test_singular_w2c(tmp_path):
    write_physg(tmp_path, TRUTH)
    cams = json.loads((tmp_path / "cam_dict_norm.json").read_text())
    cams["003.png"]["W2C"] = [0.0] * 12 + [0, 0, 0, 1]
    (tmp_path / "cam_dict_norm.json").write_text(json.dumps(cams))
    e = load_error(tmp_path)
    assert e.path.endswith("cam_dict_norm.json") and "003.png" in e.problem and "singular" in e.problem


# ---------------------------------------------------------------------------- malformed metadata

def test_malformed_json(tmp_path):
    root = nefii_scene(tmp_path)
    path = root / "transforms_train.json"
    path.write_text(path.read_text()[:-20])
    e = load_error(root)
    assert e.path.endswith("transforms_train.json") and "malformed JSON" in e.problem


def test_json_without_frames(tmp_path):
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7}))
    e = load_error(tmp_path)
    assert e.path.endswith("transforms_train.json") and "frames" in e.problem


def test_physg_entry_without_w2c(tmp_path):
    write_physg(tmp_path, TRUTH)
    cams = json.loads((tmp_path / "cam_dict_norm.json").read_text())
    del cams["001.png"]["W2C"]
    (tmp_path / "cam_dict_norm.json").write_text(json.dumps(cams))
    e = load_error(tmp_path)
    assert e.path.endswith("cam_dict_norm.json") and "'001.png'" in e.problem


def test_malformed_npz(tmp_path):
    write_neus(tmp_path, TRUTH)
    (tmp_path / "cameras_sphere.npz").write_bytes(b"PK\x03\x04 truncated")
    e = load_error(tmp_path)
    assert e.path.endswith("cameras_sphere.npz") and "not a readable .npz" in e.problem


def test_npz_missing_world_mat(tmp_path):
    write_neus(tmp_path, TRUTH)
    arrays = dict(np.load(tmp_path / "cameras_sphere.npz"))
    del arrays["world_mat_3"]
    np.savez(tmp_path / "cameras_sphere.npz", **arrays)
    e = load_error(tmp_path)
    assert e.path.endswith("cameras_sphere.npz") and "world_mat_3" in e.problem and "003.png" in e.problem


def test_neus_mask_count(tmp_path):
    write_neus(tmp_path, TRUTH)
    (tmp_path / "mask/003.png").unlink()
    e = load_error(tmp_path)
    assert e.path.endswith("mask") and "3 masks for 4 images" in e.problem


# ---------------------------------------------------------------------------- COLMAP

def test_colmap_malformed_model(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=False)
    (tmp_path / "sparse/0/cameras.txt").write_text("1 PINHOLE eight six\n")
    e = load_error(tmp_path)
    assert "sparse/0" in e.path and "not a readable COLMAP model" in e.problem


def test_colmap_rational_distortion_refused(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=True, model="FULL_OPENCV",
                 extra=(-0.1, 0.0, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0))  # k1, k2, p1, p2, k3, k4, k5, k6
    e = load_error(tmp_path)
    assert e.path.endswith("sparse/0/cameras.bin") and "camera 1 (FULL_OPENCV)" in e.problem
    assert "rational distortion terms (k4=0.01) are not supported" in e.problem and "image_undistorter" in e.problem
    assert not (tmp_path / "nefii_undistorted").exists()


def test_colmap_unsupported_camera_model_refused(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=False, model="FOV", extra=(0.9,))
    e = load_error(tmp_path)
    assert e.path.endswith("sparse/0/cameras.txt") and "camera 1 (FOV): camera model not supported" in e.problem
    assert "image_undistorter" in e.problem


def test_colmap_missing_image(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=True)
    (tmp_path / "images/r_2.png").unlink()
    e = load_error(tmp_path)
    assert e.path.endswith("images/r_2.png") and "not found" in e.problem


def test_colmap_without_pycolmap(tmp_path, monkeypatch):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=False)
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap -> ImportError
    e = load_error(tmp_path)
    assert "sparse/0" in e.path and "pip install 'nefii[colmap]'" in e.problem


# ---------------------------------------------------------------------------- what is not there

def test_no_known_format_lists_what_was_looked_for(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    e = load_error(tmp_path)
    assert e.path == str(tmp_path)
    for what in ("transforms_train.json", "_rgb.exr", "cameras_sphere.npz", "cam_dict_norm.json", "cameras.bin|txt"):
        assert what in e.problem


def test_single_split_format_has_no_test_split(tmp_path):
    write_neus(tmp_path, TRUTH)
    e = load_error(tmp_path, "test")
    assert "split 'test'" in e.problem


def test_missing_folder_and_unknown_format(tmp_path):
    assert "folder not found" in load_error(tmp_path / "nope").problem
    write_neus(tmp_path, TRUTH)
    assert "not a physg dataset" in load_error(tmp_path, format="physg").problem
    assert "unknown dataset format" in load_error(tmp_path, format="blender").problem


def test_mask_of_wrong_size(tmp_path):
    write_neus(tmp_path, TRUTH)
    Image.fromarray(np.full((H + 2, W), 255, np.uint8)).save(tmp_path / "mask/000.png")
    e = load_error(tmp_path)
    assert e.path.endswith("mask/000.png") and "same size" in e.problem


def test_some_views_with_mask_files_others_without(tmp_path):
    write_nefii(tmp_path, TRUTH, "test", extras=False)
    Image.fromarray(mask8(TRUTH, 0)).save(tmp_path / "test/r_0_mask.png")
    e = load_error(tmp_path, "test")
    assert e.path.endswith("r_1.exr") and "no mask file" in e.problem
