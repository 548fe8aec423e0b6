"""nerfstudio and instant-ngp captures: one ``transforms.json`` (what COLMAP + ``ns-process-data`` write).

    transforms.json        camera_model (PINHOLE, OPENCV or OPENCV_FISHEYE; absent: OPENCV),
                           fl_x fl_y w h, optional cx cy (else the image centre), distortion
                           k1 k2 p1 p2 k3 (OPENCV) or k1 k2 k3 k4 (OPENCV_FISHEYE), absent = 0:
                           at the top level, shared, or in a frame, which overrides;
                           frames: file_path (relative to the root), transform_matrix
                           (camera-to-world, OpenGL axes), optional mask_path;
                           optional train_filenames, test_filenames (lists of file_path)
    images/frame_00001.jpg ...    the images, wherever file_path says
    masks/frame_00001.png ...     optional masks, wherever mask_path says (white = object)
    nefii_undistorted/            written by nefii: the undistorted images and masks (``undistort``)

Poses are converted to OpenCV axes as the nerf reader does (``c2w_gl @ diag(1, -1, -1, 1)``);
the world frame is the file's. ``applied_transform`` (nerfstudio's record of how it turned
COLMAP's world) is already in every ``transform_matrix`` and is not applied again.

Distorted cameras (OPENCV with a non-zero coefficient, any OPENCV_FISHEYE) are undistorted once
with OpenCV into ``nefii_undistorted/`` and read from there with the pinhole ``K`` OpenCV chose;
PINHOLE cameras and all-zero OPENCV ones are read as they are. A coefficient the model does not
have (``k4`` for OPENCV, ``p1`` for a fisheye, any for PINHOLE) must be absent or 0. Other camera
models (EQUIRECTANGULAR, FISHEYE624, ...) are refused.

Splits: the frames listed in ``test_filenames`` are the test split and those in ``train_filenames``
(else every frame not in the test split) the training split. Without ``test_filenames`` there is
no test split. Views are in ``file_path`` order, as nerfstudio sorts them.
"""
from __future__ import annotations

import posixpath
from pathlib import Path
from typing import Any

from ..errors import InputError
from .files import IMAGE_SUFFIXES, read_json
from .nerf import frame_number, frames_of, gl_pose, intrinsics
from .scene import SceneData
from .undistort import COEFFS, Lens, check_lens_size, pinhole_views
from .assemble import View, make_scene, read_exposures, read_views

NAME = "nerfstudio"
DESCRIPTION = "transforms.json with file_path images (nerfstudio, instant-ngp)"

FILE = "transforms.json"
DEFAULT_MODEL = "OPENCV"
"""nerfstudio's reading of a file without ``camera_model``"""
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def detect(root: Path, split: str) -> bool:
    return (root / FILE).is_file()


def lens_of(meta: dict[str, Any], frame: dict[str, Any], path: Path, where: str) -> Lens:
    """A frame's camera: its own keys, falling back to the top level's."""
    def get(key: str) -> float | None:
        return frame_number(meta, frame, key, path, where)

    model = frame.get("camera_model", meta.get("camera_model", DEFAULT_MODEL))
    if model not in COEFFS:
        said = f"{where}: " if "camera_model" in frame else ""
        raise InputError(path, f"{said}camera_model {model!r} is not supported (nefii reads "
                               f"{', '.join(COEFFS)}; undistort other cameras first)")
    need = {}
    for key in ("fl_x", "fl_y", "w", "h"):
        need[key] = get(key)
        if need[key] is None:
            raise InputError(path, f"{where}: no '{key}' (at the top level or in the frame)")
    w, h = need["w"], need["h"]
    if not (w.is_integer() and h.is_integer() and w > 0 and h > 0):
        raise InputError(path, f"{where}: 'w' and 'h' must be positive whole numbers, got w={w:g}, h={h:g}")
    distortion = {k: get(k) or 0.0 for k in DISTORTION_KEYS}
    for k, v in distortion.items():
        if k not in COEFFS[model] and v != 0.0:
            raise InputError(path, f"{where}: '{k}' is {v:g} but {model} cameras have no '{k}' "
                                   f"(only {', '.join(COEFFS[model]) or 'no distortion'})")
    K = intrinsics(meta, frame, int(w), int(h), path, where)      # fl_x and fl_y are there: no field of view
    return Lens(model=model, K=K, coeffs=tuple(distortion[k] for k in COEFFS[model]), width=int(w), height=int(h))


def _view(root: Path, frame: dict[str, Any], path: Path, where: str) -> View:
    image = root / frame["file_path"]
    if image.suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(image, f"unsupported image type '{image.suffix}' (nefii reads {', '.join(IMAGE_SUFFIXES)})")
    if not image.is_file():
        raise InputError(image, f"image file not found (named in {path.name}, {where})")
    mask_path = frame.get("mask_path")
    if mask_path is None:
        return View(image=image)
    if not isinstance(mask_path, str):
        raise InputError(path, f"{where}: 'mask_path' is not a string ({mask_path!r})")
    mask = root / mask_path
    if not mask.is_file():
        raise InputError(mask, f"mask file not found (named in {path.name}, {where})")
    return View(image=image, mask=mask)


def _name(file_path: str) -> str:
    return posixpath.normpath(file_path.replace("\\", "/"))


def _listed(meta: dict[str, Any], key: str, by_name: dict[str, int], path: Path) -> set[int] | None:
    value = meta.get(key)
    if value is None:
        return None
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise InputError(path, f"'{key}' is not a list of file paths")
    missing = [v for v in value if _name(v) not in by_name]
    if missing:
        raise InputError(path, f"'{key}' lists '{missing[0]}', which is no frame's file_path"
                               + (f" ({len(missing)} such)" if len(missing) > 1 else ""))
    return {by_name[_name(v)] for v in value}


def split_frames(meta: dict[str, Any], frames: list[dict[str, Any]], split: str, path: Path) -> list[int]:
    """The frames of ``split``, in ``file_path`` order."""
    by_name = {_name(f["file_path"]): i for i, f in enumerate(frames)}
    train = _listed(meta, "train_filenames", by_name, path)
    test = _listed(meta, "test_filenames", by_name, path)
    if split == "test":
        if test is None:
            raise InputError(path, f"there is no test split in {path.name} (no 'test_filenames'; "
                                   "every frame is a training view)")
        chosen = test
    else:
        chosen = train if train is not None else set(range(len(frames))) - (test or set())
    if not chosen:
        raise InputError(path, f"the {split} split is empty")
    return sorted(chosen, key=lambda i: frames[i]["file_path"])


def read(root: Path, split: str) -> SceneData:
    path = root / FILE
    meta = read_json(path)
    frames = frames_of(meta, path)
    chosen = split_frames(meta, frames, split, path)
    lenses, views, poses = [], [], []
    for i, f in enumerate(frames):
        where = f"frame {i} ({f['file_path']})"
        poses.append(gl_pose(f, path, where))
        lenses.append(lens_of(meta, f, path, where))
        views.append(_view(root, f, path, where))
    with_mask = [v.mask is not None for v in views]
    if any(with_mask) and not all(with_mask):
        i = with_mask.index(False)
        raise InputError(path, f"frame {i} ({frames[i]['file_path']}) has no 'mask_path' while other frames do")

    # ---- undistort every distorted frame of the file (both splits share the cache)
    exposure = read_exposures([views[i] for i in chosen])
    sources, Ks = pinhole_views(root, path, views, lenses)

    stack = read_views([sources[i] for i in chosen], exposure)
    for i in chosen:
        check_lens_size(stack.images.shape[1:3], views[i].image, lenses[i], "image", path)
    return make_scene(root=root, split=split, fmt=NAME,
                      views=[views[i] for i in chosen], stack=stack,
                      K=[Ks[i] for i in chosen], c2w=[poses[i] for i in chosen])
