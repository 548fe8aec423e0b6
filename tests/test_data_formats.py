"""Each dataset reader reads a fixture of its format and returns the cameras and images it was written from."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from data_fixtures import (GL, H, NEUS_SCALE_MAT, W, make_truth, write_colmap, write_nefii, write_nerf_synthetic,
                           write_neus, write_physg, write_synthetic4relight)
from nefii.data import SceneData, load_scene
from nefii.data.undistort import CACHE_DIR, MANIFEST, Lens, undistorted_K

pytest.importorskip("OpenEXR")

TRUTH = make_truth()
CENTRED = make_truth(centred=True, seed=1)


def assert_matches(scene: SceneData, t, *, images_atol: float = 1e-6, masks: bool = True) -> None:
    """Same cameras (in the dataset's own world), intrinsics, images and masks as the truth."""
    assert (scene.height, scene.width) == (H, W) and len(scene) == t.n
    np.testing.assert_allclose(scene.source_c2w().numpy(), t.c2w, atol=1e-9)
    np.testing.assert_allclose(scene.cameras.K.numpy(), np.broadcast_to(t.K, (t.n, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(scene.images.numpy(), t.images, atol=images_atol)
    assert scene.images.dtype == torch.float32 and scene.cameras.c2w.dtype == torch.float64
    if masks:
        assert scene.masks is not None and np.array_equal(scene.masks.numpy(), t.masks)


# ---------------------------------------------------------------------------- nefii / NeRF-synthetic

def test_nefii_train_reads_exr_and_alpha_masks(tmp_path):
    write_nefii(tmp_path, TRUTH)
    scene = load_scene(tmp_path)
    assert scene.format == "nerf" and scene.split == "train"
    assert_matches(scene, TRUTH)
    assert scene.names == tuple(f"train/r_{i}.exr" for i in range(TRUTH.n))
    assert scene.indices == (0, 1, 2, 3)
    assert scene.mesh_path == tmp_path / "mesh.ply"
    assert scene.envmap is not None and scene.envmap.shape == (4, 8, 3)
    assert scene.ground_truth is None and scene.relit == ()
    assert torch.equal(scene.scene_to_source, torch.eye(4, dtype=torch.float64))


def test_nefii_test_split_ground_truth_indices_relight(tmp_path):
    write_nefii(tmp_path, TRUTH, "test", indices=[0, 5, 7, 12])
    scene = load_scene(tmp_path, "test")
    assert_matches(scene, TRUTH)
    assert scene.indices == (0, 5, 7, 12)
    gt = scene.ground_truth
    assert gt is not None
    assert gt.kinds() == ("albedo", "roughness", "specular", "diffuse", "normal", "depth", "mask")
    assert gt.albedo.shape == (4, H, W, 3) and gt.roughness.shape == (4, H, W) and gt.depth.shape == (4, H, W)
    assert np.array_equal(gt.mask.numpy(), TRUTH.masks)
    assert [r.name for r in scene.relit] == ["studio", "sunset"]
    for r in scene.relit:
        np.testing.assert_allclose(r.images.numpy(), 0.5 * TRUTH.images, atol=1e-6)
        assert r.envmap is not None and r.envmap.shape == (4, 8, 3)


def test_nefii_falls_back_to_png(tmp_path):
    write_nefii(tmp_path, TRUTH, exr=False)
    scene = load_scene(tmp_path)
    assert scene.names[0] == "train/r_0.png"
    assert_matches(scene, TRUTH)


def test_nefii_prefers_exr_over_a_named_png(tmp_path):
    write_nefii(tmp_path, TRUTH, suffix_in_path=".png")
    assert load_scene(tmp_path).names[0] == "train/r_0.exr"
    assert load_scene(tmp_path, prefer=(".png",)).names[0] == "train/r_0.png"


def test_nefii_float16_exr(tmp_path):
    write_nefii(tmp_path, TRUTH, half=True, png=False)
    assert_matches(load_scene(tmp_path), TRUTH, images_atol=2e-3)


def test_plain_nerf_synthetic(tmp_path):
    write_nerf_synthetic(tmp_path, CENTRED)
    scene = load_scene(tmp_path)
    assert scene.format == "nerf" and scene.mesh_path is None and scene.envmap is None
    assert_matches(scene, CENTRED)


# ---------------------------------------------------------------------------- Synthetic4Relight

def test_synthetic4relight_train(tmp_path):
    write_synthetic4relight(tmp_path, CENTRED)
    scene = load_scene(tmp_path)
    assert scene.format == "synthetic4relight" and scene.names[0] == "train/0_rgb.exr"
    assert_matches(scene, CENTRED)
    np.testing.assert_allclose(scene.cameras.c2w[:, :3, 3].numpy(), 0.5 * CENTRED.c2w[:, :3, 3], atol=1e-12)
    assert torch.equal(scene.scene_to_source, torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0], dtype=torch.float64)))


def test_synthetic4relight_test_ground_truth(tmp_path):
    write_synthetic4relight(tmp_path, CENTRED, "test")
    scene = load_scene(tmp_path, "test")
    assert scene.names[0] == "test/0_rgba.png"
    assert_matches(scene, CENTRED)
    gt = scene.ground_truth
    np.testing.assert_allclose(gt.albedo.numpy(), CENTRED.images, atol=1e-6)  # sRGB-decoded
    np.testing.assert_allclose(gt.roughness.numpy(), CENTRED.srgb8[..., 0] / 255.0, atol=1e-6)  # linear
    assert np.array_equal(gt.mask.numpy(), CENTRED.masks)


# ---------------------------------------------------------------------------- NeuS / IDR

def test_neus_normalises_by_scale_mat(tmp_path):
    write_neus(tmp_path, TRUTH)
    scene = load_scene(tmp_path)
    assert scene.format == "neus" and scene.names[0] == "image/000.png"
    assert_matches(scene, TRUTH)
    np.testing.assert_allclose(scene.scene_to_source.numpy(), NEUS_SCALE_MAT)
    # in nefii's world the cameras sit at scale_mat^-1 applied to the dataset's camera centres
    centres = (np.linalg.inv(NEUS_SCALE_MAT) @ np.c_[TRUTH.c2w[:, :3, 3], np.ones(TRUTH.n)].T).T[:, :3]
    np.testing.assert_allclose(scene.cameras.c2w[:, :3, 3].numpy(), centres, atol=1e-9)
    np.testing.assert_allclose(scene.cameras.c2w[:, :3, :3].numpy(), TRUTH.c2w[:, :3, :3], atol=1e-9)


def test_idr_cameras_npz_without_scale_mat(tmp_path):
    write_neus(tmp_path, TRUTH, scale_mat=None, name="cameras.npz")
    scene = load_scene(tmp_path)
    assert_matches(scene, TRUTH)
    np.testing.assert_allclose(scene.cameras.c2w.numpy(), TRUTH.c2w, atol=1e-9)


# ---------------------------------------------------------------------------- PhySG

def test_physg(tmp_path):
    write_physg(tmp_path, TRUTH)
    scene = load_scene(tmp_path)
    assert scene.format == "physg" and scene.names == tuple(f"image/{i:03d}.png" for i in range(4))
    assert_matches(scene, TRUTH)


def test_physg_split_subfolders(tmp_path):
    write_physg(tmp_path / "train", TRUTH)
    write_physg(tmp_path / "test", CENTRED)
    assert_matches(load_scene(tmp_path, "train"), TRUTH)
    assert_matches(load_scene(tmp_path, "test"), CENTRED)


# ---------------------------------------------------------------------------- COLMAP

@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
def test_colmap(tmp_path, binary):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=binary)
    scene = load_scene(tmp_path)
    assert scene.format == "colmap" and scene.names[0] == "images/r_0.png"
    assert_matches(scene, TRUTH)


def test_colmap_without_masks_simple_pinhole(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, CENTRED, binary=True, masks=False, model="SIMPLE_PINHOLE")
    scene = load_scene(tmp_path)
    assert scene.masks is None
    assert_matches(scene, CENTRED, masks=False)


OPENCV_LENS = (-0.1, 0.02, 0.002, -0.001)
"""COLMAP OPENCV's ``k1, k2, p1, p2``"""


def test_colmap_opencv_distortion_is_undistorted_once(tmp_path, capsys):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, TRUTH, binary=False, model="OPENCV", extra=OPENCV_LENS)
    scene = load_scene(tmp_path)
    K_new = undistorted_K(Lens("OPENCV", TRUTH.K, OPENCV_LENS + (0.0,), W, H))
    assert not np.allclose(K_new, TRUTH.K, atol=0.1)  # alpha 0 zooms in
    np.testing.assert_allclose(scene.cameras.K.numpy(), np.broadcast_to(K_new, (TRUTH.n, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(scene.source_c2w().numpy(), TRUTH.c2w, atol=1e-9)
    assert scene.names == tuple(f"images/r_{i}.png" for i in range(TRUTH.n))
    assert not np.allclose(scene.images.numpy(), TRUTH.images, atol=1e-2), "the images are resampled"
    assert scene.masks is not None and scene.masks.shape == (TRUTH.n, H, W)

    manifest = tmp_path / CACHE_DIR / MANIFEST
    assert json.loads(manifest.read_text())["source"] == "cameras.txt"
    assert capsys.readouterr().err.startswith("nefii: undistorted 4 images (OPENCV, k1=-0.1, k2=0.02,")
    written = manifest.stat().st_mtime_ns
    again = load_scene(tmp_path)
    assert capsys.readouterr().err == "" and manifest.stat().st_mtime_ns == written, "the cache is reused"
    assert torch.equal(again.images, scene.images) and torch.equal(again.cameras.K, scene.cameras.K)
    assert torch.equal(again.masks, scene.masks)


def test_colmap_undistorts_as_the_nerfstudio_reader_does(tmp_path):
    """The same photographs and lens, as a COLMAP model and as a transforms.json, give the same scene."""
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path / "colmap", TRUTH, binary=True, model="OPENCV", extra=OPENCV_LENS)
    shutil.copytree(tmp_path / "colmap/images", tmp_path / "ns/images")
    shutil.copytree(tmp_path / "colmap/masks", tmp_path / "ns/masks")
    (fx, _, cx), (_, fy, cy) = TRUTH.K[:2]
    frames = [{"file_path": f"images/r_{i}.png", "mask_path": f"masks/r_{i}.png.png",
               "transform_matrix": (TRUTH.c2w[i] @ GL).tolist()} for i in range(TRUTH.n)]
    (tmp_path / "ns/transforms.json").write_text(json.dumps(
        {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H,
         **dict(zip(("k1", "k2", "p1", "p2"), OPENCV_LENS)), "frames": frames}))
    colmap, ns = load_scene(tmp_path / "colmap"), load_scene(tmp_path / "ns")
    assert (colmap.format, ns.format) == ("colmap", "nerfstudio")
    np.testing.assert_allclose(colmap.cameras.K.numpy(), ns.cameras.K.numpy(), atol=1e-12)
    np.testing.assert_allclose(colmap.cameras.c2w.numpy(), ns.cameras.c2w.numpy(), atol=1e-9)
    assert torch.equal(colmap.images, ns.images) and torch.equal(colmap.masks, ns.masks)


def test_colmap_simple_radial_is_opencv_with_its_k1(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path / "simple", CENTRED, binary=True, model="SIMPLE_RADIAL", extra=(-0.1,))
    write_colmap(tmp_path / "opencv", CENTRED, binary=True, model="OPENCV", extra=(-0.1, 0.0, 0.0, 0.0))
    simple, opencv = load_scene(tmp_path / "simple"), load_scene(tmp_path / "opencv")
    assert not np.allclose(simple.cameras.K.numpy()[0], CENTRED.K, atol=0.1), "k was not ignored"
    np.testing.assert_array_equal(simple.cameras.K.numpy(), opencv.cameras.K.numpy())
    assert torch.equal(simple.images, opencv.images) and torch.equal(simple.masks, opencv.masks)


@pytest.mark.parametrize("model, extra, lens", [
    ("RADIAL", (-0.1, 0.03), Lens("OPENCV", CENTRED.K, (-0.1, 0.03, 0.0, 0.0, 0.0), W, H)),
    ("FULL_OPENCV", (-0.1, 0.03, 0.002, -0.001, 0.05, 0.0, 0.0, 0.0),
     Lens("OPENCV", CENTRED.K, (-0.1, 0.03, 0.002, -0.001, 0.05), W, H)),
    ("OPENCV_FISHEYE", (0.05, -0.01, 0.003, -0.001),
     Lens("OPENCV_FISHEYE", CENTRED.K, (0.05, -0.01, 0.003, -0.001), W, H)),
], ids=["RADIAL", "FULL_OPENCV", "OPENCV_FISHEYE"])
def test_colmap_lens_models(tmp_path, model, extra, lens):
    """Each distorted COLMAP model is the OpenCV lens with its coefficients in their places."""
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, CENTRED, binary=True, model=model, extra=extra)
    K_new = undistorted_K(lens)
    np.testing.assert_allclose(load_scene(tmp_path).cameras.K.numpy(), np.broadcast_to(K_new, (CENTRED.n, 3, 3)),
                               atol=1e-9)
    manifest = json.loads((tmp_path / CACHE_DIR / MANIFEST).read_text())
    assert [v["model"] for v in manifest["views"]] == [lens.model] * CENTRED.n
    assert manifest["views"][0]["coeffs"] == list(lens.coeffs)


# ---------------------------------------------------------------------------- all agree

def test_every_format_gives_the_nefii_cameras(tmp_path):
    """The nefii layout and every other format written from the same scene give the same cameras and images."""
    pytest.importorskip("pycolmap")
    writers = {
        "nefii": lambda p, t: write_nefii(p, t),
        "nerf-synthetic": write_nerf_synthetic, "synthetic4relight": write_synthetic4relight,
        "neus": write_neus, "physg": write_physg,
        "colmap-text": lambda p, t: write_colmap(p, t, binary=False),
        "colmap-binary": lambda p, t: write_colmap(p, t, binary=True),
    }
    for name, write in writers.items():
        write(tmp_path / name, CENTRED)
    ref = load_scene(tmp_path / "nefii")
    for name in writers:
        scene = load_scene(tmp_path / name)
        np.testing.assert_allclose(scene.source_c2w().numpy(), ref.cameras.c2w.numpy(), atol=1e-9, err_msg=name)
        np.testing.assert_allclose(scene.cameras.K.numpy(), ref.cameras.K.numpy(), atol=1e-9, err_msg=name)
        np.testing.assert_allclose(scene.images.numpy(), ref.images.numpy(), atol=1e-6, err_msg=name)
        assert torch.equal(scene.masks, ref.masks), name


def test_transparent_backgrounds_are_flagged(tmp_path):
    """RGBA renders (masks from alpha) observe nothing off the object; photos with mask files do."""
    from data_fixtures import make_truth, write_nefii, write_physg

    from nefii.data import load_scene

    t = make_truth()
    write_nefii(tmp_path / "rgba", t)
    assert load_scene(tmp_path / "rgba").background_visible is False
    write_physg(tmp_path / "photos", t)
    assert load_scene(tmp_path / "photos").background_visible is True
