"""SceneData's own contract and the readers' building blocks."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from PIL import Image

from data_fixtures import make_truth, write_nefii
from nefii.data import FORMATS, load_scene
from nefii.data.files import read_image
from nefii.data.neus import decompose_projection
from nefii.data.assemble import frame_indices
from nefii.errors import InputError
from nefii.io.exr import write_exr
from nefii.io.images import srgb_to_linear

TRUTH = make_truth()


@pytest.fixture(scope="module")
def test_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("nefii")
    write_nefii(root, TRUTH, "test")
    return load_scene(root, "test")


def test_to_moves_every_tensor(test_scene):
    moved = test_scene.to("meta")
    assert moved.images.device.type == "meta" and moved.cameras.c2w.device.type == "meta"
    assert moved.masks.device.type == "meta" and moved.envmap.device.type == "meta"
    assert all(getattr(moved.ground_truth, k).device.type == "meta" for k in moved.ground_truth.kinds())
    assert all(r.images.device.type == "meta" for r in moved.relit)
    assert moved.cameras.c2w.dtype == torch.float64 and moved.images.dtype == torch.float32
    assert test_scene.images.device.type == "cpu"  # the original is untouched


def test_scene_checks_its_shapes(test_scene):
    with pytest.raises(ValueError, match="masks must be bool"):
        dataclasses.replace(test_scene, masks=test_scene.masks.float())
    with pytest.raises(ValueError, match="names"):
        dataclasses.replace(test_scene, names=test_scene.names[:2])
    with pytest.raises(ValueError, match="images must be"):
        dataclasses.replace(test_scene, images=test_scene.images[..., :2])


def test_source_c2w_undoes_a_similarity(test_scene):
    """A rotated, scaled, shifted normalisation is undone exactly."""
    c, s = math.cos(0.3), math.sin(0.3)
    S = torch.tensor([[2 * c, -2 * s, 0, 1.0], [2 * s, 2 * c, 0, -2.0], [0, 0, 2, 0.5], [0, 0, 0, 1]],
                     dtype=torch.float64)
    scene = dataclasses.replace(test_scene, scene_to_source=S)
    expected = S @ test_scene.cameras.c2w @ torch.diag(torch.tensor([0.5, 0.5, 0.5, 1.0], dtype=torch.float64))
    torch.testing.assert_close(scene.source_c2w(), expected)


def test_decompose_projection_matches_known_camera():
    K = np.array([[300.0, 0.5, 160.0], [0, 280.0, 120.0], [0, 0, 1]])
    c2w = TRUTH.c2w[1]
    P = -3.7 * K @ np.linalg.inv(c2w)[:3]  # any non-zero scale, even negative, is the same camera
    K2, c2w2 = decompose_projection(P, "x.npz", "world_mat_0")
    np.testing.assert_allclose(K2, K, atol=1e-9)
    np.testing.assert_allclose(c2w2, c2w, atol=1e-9)


def test_frame_indices():
    assert frame_indices(["r_0", "r_12", "r_3"]) == (0, 12, 3)
    assert frame_indices(["a", "b_1"]) == (0, 1)  # not all numbered: positions
    assert frame_indices(["x_1", "y_1"]) == (0, 1)  # duplicates: positions


def test_rgba_exr_is_unpremultiplied(tmp_path):
    rgb = np.array([[[0.2, 0.4, 8.0], [1.0, 1.0, 1.0]]], np.float32)
    alpha = np.array([[0.25, 0.0]], np.float32)
    write_exr(tmp_path / "a.exr", np.concatenate([rgb * alpha[..., None], alpha[..., None]], -1))
    img = read_image(tmp_path / "a.exr")
    out, a = img.rgb, img.alpha
    assert img.clipped is None  # float data cannot clip
    np.testing.assert_allclose(out[0, 0], rgb[0, 0], rtol=1e-6)
    np.testing.assert_array_equal(out[0, 1], 0.0)  # alpha 0: left as stored
    np.testing.assert_array_equal(a, alpha)


def test_png_is_srgb_decoded_and_grey_repeated(tmp_path):
    Image.fromarray(np.array([[0, 128, 255]], np.uint8)).save(tmp_path / "g.png")
    img = read_image(tmp_path / "g.png")
    out, a = img.rgb, img.alpha
    assert out.shape == (1, 3, 3) and a is None
    np.testing.assert_allclose(out[0, :, 0], srgb_to_linear(np.array([0, 128, 255]) / 255.0))


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_8bit_pixels_at_the_top_code_are_clipped(tmp_path, suffix):
    """Any channel at 254 or 255 is clipped; 253 and below is not (JPEG stored losslessly enough here:
    flat 8x8 blocks of one value)."""
    vals = [(0, 0, 0), (253, 253, 253), (254, 10, 10), (10, 255, 10), (100, 100, 100)]
    arr = np.concatenate([np.full((8, 8, 3), v, np.uint8) for v in vals], axis=1)
    Image.fromarray(arr).save(tmp_path / f"c{suffix}", quality=100)
    clipped = read_image(tmp_path / f"c{suffix}").clipped
    got = [bool(clipped[2:6, 8 * i + 2:8 * i + 6].all()) for i in range(len(vals))]
    none = [not bool(clipped[2:6, 8 * i + 2:8 * i + 6].any()) for i in range(len(vals))]
    assert got == [False, False, True, True, False] and none == [True, True, False, False, True]


def test_16bit_png_clips_only_at_its_own_top(tmp_path):
    Image.fromarray(np.array([[65535, 65280, 0]], np.uint16)).save(tmp_path / "d.png")
    clipped = read_image(tmp_path / "d.png").clipped
    assert clipped.tolist() == [[True, False, False]]  # 65280 = 255 * 256 is not the top of 16 bits


def test_unsupported_image_suffix(tmp_path):
    (tmp_path / "x.webp").write_bytes(b"")
    with pytest.raises(InputError, match="unsupported image type"):
        read_image(tmp_path / "x.webp")


def test_formats_are_described():
    for name, fmt in FORMATS.items():
        assert fmt.name == name and fmt.description


def test_rgba_ground_truth_map_is_unpremultiplied(tmp_path):
    from nefii.data.files import read_data_map

    write_exr(tmp_path / "n.exr", np.array([[[0.0, 0.25, 0.5, 0.5], [0.0, 0.0, 0.0, 0.0]]], np.float32))
    np.testing.assert_allclose(read_data_map(tmp_path / "n.exr", 3), [[[0.0, 0.5, 1.0], [0.0, 0.0, 0.0]]])
    np.testing.assert_allclose(read_data_map(tmp_path / "n.exr", 1), [[[0.0], [0.0]]])
