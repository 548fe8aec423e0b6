"""The nerfstudio / instant-ngp reader: a tiny phone-like capture photographed through a known lens.

Each photograph is rendered analytically: its pixel centres are taken back through the lens (OpenCV's
own ``undistortPoints``) to ideal pinhole coordinates, where a smooth pattern and a disc-shaped
object are evaluated. After nefii undistorts it, the image must show the same pattern at the pixel
centres of the ``K`` it reports, and that ``K`` must be the one OpenCV picks.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from data_fixtures import GL, make_truth
from nefii.data import load_scene
from nefii.data.undistort import CACHE_DIR
from nefii.errors import InputError
from nefii.io.images import srgb_to_linear

W, H = 64, 48
K = np.array([[52.0, 0.0, 33.0], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
OPENCV = {"k1": -0.1, "k2": 0.02, "p1": 0.001, "p2": -0.0015}
FISHEYE = {"k1": 0.05, "k2": -0.01, "k3": 0.003, "k4": -0.001}
ORDER = {"OPENCV": ("k1", "k2", "p1", "p2", "k3"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"), "PINHOLE": ()}
HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
"""nefii's pixel centres (j + 0.5) from OpenCV's (j)"""
TRUTH = make_truth(3)
APPLIED = [[0.0, 1.0, 0.0, 0.2], [1.0, 0.0, 0.0, -0.1], [0.0, 0.0, -1.0, 0.3]]
"""an ``applied_transform`` the reader must not apply"""


# ---------------------------------------------------------------------------- the capture

def pattern(xy: np.ndarray, k: int) -> np.ndarray:
    """sRGB values in [0, 1] of frame ``k``'s scene at ideal normalised coordinates ``xy`` (..., 2)."""
    x, y = xy[..., 0] + 0.05 * k, xy[..., 1]
    return np.stack([0.5 + 0.4 * np.sin(18 * x + 1) * np.cos(14 * y), 0.5 + 0.4 * np.cos(12 * x - 16 * y),
                     0.45 + 0.3 * x + 0.2 * np.sin(22 * y)], -1).clip(0, 1)


def inside(xy: np.ndarray) -> np.ndarray:
    """The object: a disc in normalised coordinates."""
    return np.hypot(xy[..., 0] - 0.05, xy[..., 1] + 0.03) < 0.32


def centres(K_: np.ndarray) -> np.ndarray:
    """Ideal normalised coordinates (H, W, 2) of a pinhole camera's pixel centres (nefii's convention)."""
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return np.stack([(j - K_[0, 2]) / K_[0, 0], (i - K_[1, 2]) / K_[1, 1]], -1)


def through_lens(model: str, coeffs: dict[str, float]) -> np.ndarray:
    """Ideal normalised coordinates (H, W, 2) that the photograph's pixel centres see, via OpenCV."""
    D = np.array([coeffs.get(k, 0.0) for k in ORDER[model]])
    j, i = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([j, i], -1).reshape(-1, 1, 2)  # OpenCV's pixel centres, with K shifted to match
    K_cv = np.linalg.inv(HALF) @ K
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    if model == "OPENCV_FISHEYE":
        xy = cv2.fisheye.undistortPoints(pts, K_cv, D, criteria=crit)
        back, _ = cv2.fisheye.projectPoints(np.concatenate([xy, np.ones_like(xy[..., :1])], -1), np.zeros(3),
                                            np.zeros(3), K_cv, D)
    else:
        xy = cv2.undistortPoints(pts, K_cv, D, criteria=crit)
        back, _ = cv2.projectPoints(np.concatenate([xy, np.ones_like(xy[..., :1])], -1)[:, 0], np.zeros(3),
                                    np.zeros(3), K_cv, D)
    assert np.abs(back.reshape(-1, 2) - pts.reshape(-1, 2)).max() < 1e-6  # the inverse is exact
    return xy.reshape(H, W, 2)


def u8(values: np.ndarray) -> np.ndarray:
    return (np.clip(values, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_capture(root: Path, model: str = "OPENCV", coeffs: dict[str, float] | None = None, *,
                  suffix: str = ".png", masks: bool = True, **top) -> dict:
    """Three frames ``images/frame_0000{1,2,3}``, masks ``masks/frame_0000k.png``; returns the json."""
    coeffs = OPENCV if coeffs is None and model == "OPENCV" else (coeffs or {})
    xy = centres(K) if model == "PINHOLE" else through_lens(model, coeffs)
    frames = []
    for k in range(TRUTH.n):
        name = f"frame_{k + 1:05d}"
        (root / "images").mkdir(parents=True, exist_ok=True)
        Image.fromarray(u8(pattern(xy, k))).save(root / "images" / f"{name}{suffix}", quality=98)
        frame = {"file_path": f"images/{name}{suffix}", "transform_matrix": (TRUTH.c2w[k] @ GL).tolist()}
        if masks:
            (root / "masks").mkdir(exist_ok=True)
            Image.fromarray(np.where(inside(xy), 255, 0).astype(np.uint8)).save(root / "masks" / f"{name}.png")
            frame["mask_path"] = f"masks/{name}.png"
        frames.append(frame)
    meta = {"camera_model": model, "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": W, "h": H,
            **coeffs, "applied_transform": APPLIED, "frames": frames[::-1], **top}  # file order is not view order
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return meta


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


CENTRE = (slice(6, -6), slice(8, -8))
"""the valid centre compared, away from the border where the point-sampled test photographs alias"""


def rim_distance(ideal: np.ndarray, K_: np.ndarray) -> np.ndarray:
    """Each pixel's distance to the object's rim, in pixels."""
    return np.abs(np.hypot(ideal[..., 0] - 0.05, ideal[..., 1] + 0.03) - 0.32) * K_[0, 0]


def assert_undistorted(scene, model: str, coeffs: dict[str, float], K_new: np.ndarray, *, psnr_above: float,
                       raw_psnr_below: float) -> float:
    """Images show the pattern at ``K_new``'s pixel centres (in the valid centre), the photographs as they are
    would not; masks differ from the truth only within half a pixel of the rim. Returns how far from the rim
    the photographs' own masks differ (pixels)."""
    ideal, photo = centres(K_new), through_lens(model, coeffs)
    for k in range(len(scene)):
        truth = srgb_to_linear(pattern(ideal, k))[CENTRE]
        got = scene.images[k].numpy()[CENTRE]
        raw = srgb_to_linear(u8(pattern(photo, k)) / 255.0)[CENTRE]
        assert psnr(got, truth) > psnr_above and np.abs(got - truth).max() < 0.04, (psnr(got, truth),
                                                                                    np.abs(got - truth).max())
        assert psnr(raw, truth) < raw_psnr_below, psnr(raw, truth)
        wrong = scene.masks[k].numpy() != inside(ideal)
        assert rim_distance(ideal, K_new)[wrong].max(initial=0.0) < 0.5
    raw_wrong = inside(photo) != inside(ideal)
    return float(rim_distance(ideal, K_new)[raw_wrong].max(initial=0.0))


def cache_files(root: Path) -> dict[Path, tuple[int, int]]:
    return {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in (root / CACHE_DIR).rglob("*") if p.is_file()}


def message(capsys) -> list[str]:
    captured = capsys.readouterr()
    return [line for line in (captured.err + captured.out).splitlines() if line]


# ---------------------------------------------------------------------------- reading

def test_opencv_capture_is_undistorted_to_the_pinhole_truth(tmp_path, capsys):
    write_capture(tmp_path)
    scene = load_scene(tmp_path)
    assert scene.format == "nerfstudio" and scene.split == "train" and len(scene) == 3
    assert scene.names == ("images/frame_00001.png", "images/frame_00002.png", "images/frame_00003.png")
    assert scene.indices == (1, 2, 3)

    # the new K is OpenCV's (alpha 0), moved between OpenCV's pixel centres and nefii's
    D = np.array([OPENCV["k1"], OPENCV["k2"], OPENCV["p1"], OPENCV["p2"], 0.0])
    K_cv, _ = cv2.getOptimalNewCameraMatrix(np.linalg.inv(HALF) @ K, D, (W, H), 0, (W, H))
    K_new = HALF @ K_cv
    np.testing.assert_allclose(scene.cameras.K.numpy(), np.broadcast_to(K_new, (3, 3, 3)), atol=1e-9)
    assert not np.allclose(K_new, K, atol=0.5)  # alpha 0 zooms in

    # poses: OpenGL -> OpenCV, applied_transform not applied again
    np.testing.assert_allclose(scene.cameras.c2w.numpy(), TRUTH.c2w, atol=1e-9)

    # images and masks: the truth at the new K's pixel centres; the photographs as they are are not.
    # (At 64 x 48, k1 = -0.1 moves the interior by under half a pixel, so only the fisheye test can tell
    # resampled masks from the photographs' own.)
    assert_undistorted(scene, "OPENCV", OPENCV, K_new, psnr_above=45, raw_psnr_below=38)

    lines = message(capsys)
    assert len(lines) == 1 and lines[0].startswith("nefii: undistorted 3 images (OPENCV, k1=-0.1, k2=0.02,"), lines
    assert str(tmp_path / CACHE_DIR) in lines[0]
    assert sorted(p.name for p in (tmp_path / CACHE_DIR / "images").iterdir()) == [
        "00000_frame_00003.png", "00001_frame_00002.png", "00002_frame_00001.png"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no temporary folder left"


def test_the_cache_is_reused_until_the_json_or_an_image_changes(tmp_path, capsys):
    write_capture(tmp_path)
    first = load_scene(tmp_path)
    assert len(message(capsys)) == 1
    files = cache_files(tmp_path)
    assert len(files) == 7  # 3 images, 3 masks, the manifest

    again = load_scene(tmp_path)
    assert message(capsys) == [] and cache_files(tmp_path) == files, "reused: no message, nothing rewritten"
    assert np.array_equal(again.images.numpy(), first.images.numpy())
    assert np.array_equal(again.masks.numpy(), first.masks.numpy())
    assert np.array_equal(again.cameras.K.numpy(), first.cameras.K.numpy())

    img = np.array(Image.open(tmp_path / "images/frame_00002.png"))
    img[10, 10] = 255 - img[10, 10]
    Image.fromarray(img).save(tmp_path / "images/frame_00002.png")
    load_scene(tmp_path)
    assert len(message(capsys)) == 1, "a changed image is redone"

    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["k1"] = -0.12
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    changed = load_scene(tmp_path)
    assert len(message(capsys)) == 1, "a changed transforms.json is redone"
    assert not np.allclose(changed.cameras.K.numpy(), first.cameras.K.numpy())


def test_fisheye_capture(tmp_path, capsys):
    write_capture(tmp_path, "OPENCV_FISHEYE", FISHEYE)
    scene = load_scene(tmp_path)
    D = np.array([FISHEYE[k] for k in ORDER["OPENCV_FISHEYE"]])
    K_cv = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(np.linalg.inv(HALF) @ K, D, (W, H), np.eye(3),
                                                                  balance=0.0)
    K_new = HALF @ K_cv
    np.testing.assert_allclose(scene.cameras.K.numpy(), np.broadcast_to(K_new, (3, 3, 3)), atol=1e-9)
    mask_rims = assert_undistorted(scene, "OPENCV_FISHEYE", FISHEYE, K_new, psnr_above=43, raw_psnr_below=30)
    assert mask_rims > 0.5, "a fisheye moves the rim by more than half a pixel: the masks were resampled"
    assert message(capsys)[0].startswith("nefii: undistorted 3 images (OPENCV_FISHEYE, k1=0.05,")


def test_jpeg_photographs_are_cached_as_8_bit_png(tmp_path, capsys):
    write_capture(tmp_path, suffix=".jpg")
    scene = load_scene(tmp_path)
    cached = sorted((tmp_path / CACHE_DIR / "images").iterdir())
    assert [p.suffix for p in cached] == [".png"] * 3
    with Image.open(cached[0]) as im:
        assert im.mode == "RGB" and im.size == (W, H)
    truth = srgb_to_linear(pattern(centres(scene.cameras.K[0].numpy()), 0))
    assert psnr(scene.images[0].numpy(), truth) > 33
    assert scene.names[0] == "images/frame_00001.jpg"


def test_pinhole_capture_is_read_as_it_is_with_per_frame_intrinsics(tmp_path, capsys):
    meta = write_capture(tmp_path, "PINHOLE", masks=False)
    meta["frames"][0]["fl_x"] = 60.0  # frame_00003: its own focal length
    meta["frames"][0]["cx"] = 31.0
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path)
    assert not (tmp_path / CACHE_DIR).exists() and message(capsys) == []
    Ks = scene.cameras.K.numpy()
    np.testing.assert_allclose(Ks[:2], np.broadcast_to(K, (2, 3, 3)))
    np.testing.assert_allclose(Ks[2], [[60.0, 0, 31.0], [0, K[1, 1], K[1, 2]], [0, 0, 1]])
    np.testing.assert_allclose(scene.images[0].numpy(), srgb_to_linear(u8(pattern(centres(K), 0)) / 255.0), atol=1e-6)
    assert scene.masks is None


def test_all_zero_opencv_coefficients_need_no_undistortion(tmp_path, capsys):
    write_capture(tmp_path, "OPENCV", {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    scene = load_scene(tmp_path)
    assert not (tmp_path / CACHE_DIR).exists() and message(capsys) == []
    np.testing.assert_allclose(scene.cameras.K.numpy(), np.broadcast_to(K, (3, 3, 3)))
    assert np.array_equal(scene.masks[0].numpy(), inside(centres(K)))


def test_train_and_test_filenames_split_the_frames(tmp_path, capsys):
    write_capture(tmp_path, train_filenames=["images/frame_00001.png", "./images/frame_00003.png"],
                  test_filenames=["images/frame_00002.png"])
    train, test = load_scene(tmp_path, "train"), load_scene(tmp_path, "test")
    assert train.names == ("images/frame_00001.png", "images/frame_00003.png") and train.indices == (1, 3)
    assert test.names == ("images/frame_00002.png",) and test.split == "test"
    np.testing.assert_allclose(test.cameras.c2w.numpy()[0], TRUTH.c2w[1], atol=1e-9)
    assert len(message(capsys)) == 1, "both splits share one undistortion"


def test_test_filenames_alone_leave_the_rest_for_training(tmp_path):
    write_capture(tmp_path, test_filenames=["images/frame_00003.png"])
    assert load_scene(tmp_path).indices == (1, 2)


def test_detection_beside_the_nerf_layout(tmp_path):
    write_capture(tmp_path, "PINHOLE")
    assert load_scene(tmp_path).format == "nerfstudio"
    meta = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    assert load_scene(tmp_path).format == "nerf"  # transforms_{split}.json is the nerf layout's
    assert load_scene(tmp_path, format="nerfstudio").format == "nerfstudio"


# ---------------------------------------------------------------------------- bad input

def load_error(root: Path, split: str = "train") -> InputError:
    with pytest.raises(InputError) as info:
        load_scene(root, split)
    e = info.value
    assert "\n" not in str(e) and e.exit_code == 2
    return e


def edit_json(root: Path, change) -> None:
    meta = json.loads((root / "transforms.json").read_text())
    change(meta)
    (root / "transforms.json").write_text(json.dumps(meta))


def resize(path: Path) -> None:
    with Image.open(path) as im:
        im.resize((W + 2, H)).save(path)


BAD = {
    # name: (model, break it, file named, words)
    "missing image": ("OPENCV", lambda r: (r / "images/frame_00002.png").unlink(), "images/frame_00002.png",
                      ("image file not found",)),
    "missing image, pinhole": ("PINHOLE", lambda r: (r / "images/frame_00002.png").unlink(),
                               "images/frame_00002.png", ("image file not found",)),
    "image size is not w x h": ("OPENCV", lambda r: resize(r / "images/frame_00002.png"), "images/frame_00002.png",
                                (f"{W + 2}x{H}", f"w={W}, h={H}")),
    "image size is not w x h, pinhole": ("PINHOLE", lambda r: edit_json(r, lambda m: m.update(w=W + 2)),
                                         "images/frame_00001.png", (f"{W}x{H}", f"w={W + 2}")),
    "mask size": ("OPENCV", lambda r: resize(r / "masks/frame_00003.png"), "masks/frame_00003.png",
                  ("mask is", f"{W + 2}x{H}")),
    "mask size, pinhole": ("PINHOLE", lambda r: resize(r / "masks/frame_00003.png"), "masks/frame_00003.png",
                           (f"{W + 2}x{H}",)),
    "missing mask": ("OPENCV", lambda r: (r / "masks/frame_00001.png").unlink(), "masks/frame_00001.png",
                     ("mask file not found",)),
    "no fl_x": ("OPENCV", lambda r: edit_json(r, lambda m: m.pop("fl_x")), "transforms.json", ("'fl_x'",)),
    "no fl_y": ("OPENCV", lambda r: edit_json(r, lambda m: m.pop("fl_y")), "transforms.json", ("'fl_y'",)),
    "unreadable json": ("OPENCV", lambda r: (r / "transforms.json").write_text("{\"frames\": [,]}"),
                        "transforms.json", ("malformed JSON",)),
    "NaN in a matrix": ("OPENCV", lambda r: edit_json(r, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(
        3, float("nan"))), "transforms.json", ("frame 1", "NaN")),
    "other camera model": ("OPENCV", lambda r: edit_json(r, lambda m: m.update(camera_model="EQUIRECTANGULAR")),
                           "transforms.json", ("'EQUIRECTANGULAR'", "not supported")),
    "a coefficient the model lacks": ("PINHOLE", lambda r: edit_json(r, lambda m: m.update(k1=-0.1)),
                                      "transforms.json", ("'k1' is -0.1", "PINHOLE")),
    "absurd EXIF exposure time": ("OPENCV", lambda r: with_exif(r / "images/frame_00002.png", 0.0),
                                  "images/frame_00002.png", ("ExposureTime", "absurd")),
    "EXIF exposures 31.5 stops apart": ("OPENCV", lambda r: [with_exif(r / f"images/frame_0000{k}.png", t, iso)
                                                           for k, t, iso in ((1, 0.01, 100), (2, 0.01, 100),
                                                                             (3, 3000.0, 10**6))],
                                      "images/frame_00003.png", ("span 31.5 stops", "absurd")),
    "listed file is no frame": ("OPENCV", lambda r: edit_json(r, lambda m: m.update(test_filenames=["images/x.png"])),
                                "transforms.json", ("test_filenames", "images/x.png")),
}


def with_exif(path: Path, seconds: float, iso: int = 100, f_number: float = 1.8) -> None:
    """Re-save an image with a phone's EXIF exposure fields."""
    from PIL import ExifTags

    with Image.open(path) as im:
        im.load()
        exif = Image.Exif()
        exif[ExifTags.IFD.Exif] = {ExifTags.Base.ExposureTime: seconds, ExifTags.Base.FNumber: f_number,
                                   ExifTags.Base.ISOSpeedRatings: iso}
        im.save(path, exif=exif)


def test_exif_exposures_are_read_when_every_photo_has_one(tmp_path):
    write_capture(tmp_path)
    assert load_scene(tmp_path).exposure is None
    times = {1: 1 / 50, 2: 1 / 100, 3: 1 / 400}
    for k, t in times.items():
        with_exif(tmp_path / f"images/frame_0000{k}.png", t, iso=200, f_number=2.0)
    scene = load_scene(tmp_path)
    want = [times[int(n[-5])] * 200 / 4.0 for n in scene.names]
    np.testing.assert_allclose(scene.exposure.numpy(), want, rtol=1e-6)


def test_exif_on_some_photos_only_is_not_used(tmp_path):
    write_capture(tmp_path)
    with_exif(tmp_path / "images/frame_00001.png", 1 / 100)
    with pytest.warns(UserWarning, match="no EXIF exposure"):
        assert load_scene(tmp_path).exposure is None


@pytest.mark.parametrize("name", BAD)
def test_bad_input_names_the_file(tmp_path, name, capsys):
    model, breaks, named, words = BAD[name]
    write_capture(tmp_path, model)
    breaks(tmp_path)
    e = load_error(tmp_path)
    assert e.path == str(tmp_path / named), e
    for w in words:
        assert w in e.problem, (w, str(e))
    assert not (tmp_path / CACHE_DIR).exists() and message(capsys) == [], "nothing written on bad input"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no temporary folder left"


def test_no_test_split_is_an_error(tmp_path):
    write_capture(tmp_path, "PINHOLE")
    e = load_error(tmp_path, "test")
    assert e.path == str(tmp_path / "transforms.json") and "no test split in transforms.json" in e.problem


def test_a_bad_image_keeps_the_previous_cache(tmp_path, capsys):
    write_capture(tmp_path)
    load_scene(tmp_path)
    files = cache_files(tmp_path)
    (tmp_path / "images/frame_00001.png").write_bytes(b"not a png")
    e = load_error(tmp_path)
    assert e.path == str(tmp_path / "images/frame_00001.png")
    assert cache_files(tmp_path) == files
