"""``synth --photo``: the phone's capture of a clean scene, read back through the nerfstudio reader."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from fit_fixtures import write_rendered_scene
from nefii.data import load_scene
from nefii.data.downscale import downscaled
from nefii.errors import InputError
from nefii.synth.photo import PhotoSettings, distort, distortion_maps, make_photos, photo_K

pytest.importorskip("cv2")

SIZE = 96
K_RENDER = np.array([[90.0, 0.0, SIZE / 2], [0.0, 90.0, SIZE / 2], [0.0, 0.0, 1.0]])
D = np.array([-0.1, 0.01, 0.0, 0.0])


def dots(points: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Gaussian dots centred at ``points`` (nefii pixel coordinates: pixel (i, j)'s centre is (j+.5, i+.5))."""
    j, i = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    img = sum(np.exp(-((j - x) ** 2 + (i - y) ** 2) / (2 * sigma**2)) for x, y in points)
    return np.repeat(img[..., None], 3, -1).astype(np.float32)


def centroid(img: np.ndarray, near: np.ndarray, radius: int = 5) -> np.ndarray:
    x0, y0 = int(near[0]), int(near[1])
    win = img[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1, 0].astype(np.float64)
    win = np.clip(win - np.median(img[..., 0]), 0, None)
    j, i = np.meshgrid(np.arange(x0 - radius, x0 + radius + 1) + 0.5, np.arange(y0 - radius, y0 + radius + 1) + 0.5)
    return np.array([(win * j).sum(), (win * i).sum()]) / win.sum()


def test_a_distorted_view_undistorts_onto_its_pinhole_twin_within_half_a_pixel(tmp_path):
    """Dots drawn in a pinhole render, distorted as the phone's lens does, written as a nerfstudio capture
    and read back (undistorted by OpenCV onto the pinhole K it picks): each dot lands where that K puts
    the ray of the render's dot."""
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(14, SIZE - 10, 17.0), np.arange(14, SIZE - 10, 17.0)), -1).reshape(-1, 2)
    points = grid + rng.uniform(-2, 2, grid.shape)  # 17 px apart: one dot per centroid window
    K_photo = photo_K(K_RENDER, D, SIZE, SIZE)
    assert K_photo[0, 0] > K_RENDER[0, 0]  # zoomed in: barrel distortion looks wider than the pinhole
    photo = distort(dots(points), distortion_maps(K_RENDER, K_photo, D, SIZE, SIZE))
    (tmp_path / "images").mkdir()
    Image.fromarray((np.clip(photo, 0, 1) * 65535).astype(np.uint16)[..., 0]).save(tmp_path / "images" / "a.png")
    (tmp_path / "transforms.json").write_text(json.dumps({
        "camera_model": "OPENCV", "w": SIZE, "h": SIZE, "fl_x": K_photo[0, 0], "fl_y": K_photo[1, 1],
        "cx": K_photo[0, 2], "cy": K_photo[1, 2], "k1": D[0], "k2": D[1],
        "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}))
    scene = load_scene(tmp_path)
    K_new = scene.cameras.K[0].numpy()
    img = scene.images[0].numpy()
    rays = np.linalg.solve(K_RENDER, np.concatenate([points, np.ones((len(points), 1))], 1).T)
    want = (K_new @ rays)[:2].T
    inside = [w for w in want if 8 < w.min() and w.max() < SIZE - 8]  # away from the border the crop cuts
    assert len(inside) >= 16
    for w in inside:
        got = centroid(img, w)
        assert np.linalg.norm(got - w) < 0.5, (got, w)


def test_make_photos_writes_a_capture_the_nerfstudio_reader_takes(tmp_path):
    clean = write_rendered_scene(tmp_path / "clean", res=24, n_train=4, n_test=2)
    out = make_photos(clean, tmp_path / "photo", PhotoSettings(seed=3))
    train, test = load_scene(out, "train"), load_scene(out, "test")
    assert (len(train), len(test)) == (4, 2) and train.format == "nerfstudio"
    assert train.masks is None  # a phone takes no masks
    assert (out / "nefii_undistorted").is_dir()  # the lens was undistorted on the way in
    record = json.loads((out / "photo.json").read_text())
    stops = np.array([v["stops"] for v in record["views"]])
    assert np.all(np.abs(stops) <= 1.0) and stops.std() > 0.1  # a different exposure per view, within +-1 EV
    with Image.open(out / record["views"][0]["file_path"]) as im:
        assert im.format == "JPEG" and im.mode == "RGB"
    exposure = np.concatenate([train.exposure.numpy(), test.exposure.numpy()])  # the EXIF a phone writes
    np.testing.assert_allclose(np.log2(exposure / exposure[0]), stops - stops[0], atol=1e-4)
    assert [v["clean"] for v in record["views"]] == ["train/r_0.exr", "train/r_1.exr", "train/r_2.exr",
                                                      "train/r_3.exr", "test/r_0.exr", "test/r_1.exr"]


def test_photos_from_a_finer_render_are_at_its_resolution_and_average_down(tmp_path):
    clean = write_rendered_scene(tmp_path / "clean", res=16, n_train=3, n_test=1)
    fine = write_rendered_scene(tmp_path / "fine", res=32, n_train=3, n_test=1)
    out = make_photos(clean, tmp_path / "photo", PhotoSettings(seed=1), render=fine)
    with Image.open(out / "images" / "frame_00001.jpg") as im:
        assert im.size == (32, 32)
    scene, factor = downscaled(load_scene(out, "train"), 16)
    assert factor == 2 and (scene.width, scene.height) == (16, 16)


def test_a_render_of_other_views_is_refused(tmp_path):
    clean = write_rendered_scene(tmp_path / "clean", res=16, n_train=3, n_test=1)
    other = write_rendered_scene(tmp_path / "other", res=32, n_train=2, n_test=1)
    with pytest.raises(InputError, match="integer multiple"):
        make_photos(clean, tmp_path / "photo", PhotoSettings(), render=other)
    assert not (tmp_path / "photo").exists()
