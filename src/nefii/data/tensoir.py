"""The TensoIR synthetic layout (Jin et al., CVPR 2023: lego, hotdog, armadillo, ficus), as TensoIR's loaders read it;
NeRFactor's per-view folders (Zhang et al. 2021), from which it comes, have the same files and keys.

    <scene>/train_000/, train_001/, ...   one folder a view (TensoIR ships 100 training and 200 test views)
        metadata.json                       imw, imh; cam_angle_x (radians); cam_transform_mat: Blender's
                                            camera-to-world (OpenGL axes), 16 comma-separated numbers, row-major
        rgba.png                            the view: sRGB, alpha = coverage (the mask)
        albedo.png                          optional ground truth: sRGB-encoded albedo, alpha
    <scene>/test_000/, ...                  the same, and optionally
        rgba_<env>.png                      the view under another light (TensoIR: bridge, city, fireplace,
                                            forest, night), read as the relit set ``<env>``

``fx = fy = imw / (2 tan(cam_angle_x / 2))``, principal point at the image centre, as TensoIR's loaders. Other
files in a view's folder (``normal.png``, TensoIR's rotated-light ``rgba_<env>_<deg>.png`` when that name has
no plain ``rgba_<env>.png`` in every view) are not read. The environment maps live outside the scene folder
(TensoIR's ``Environment_Maps``), in Blender's world mapping, which is nefii's: ``nefii relight RUN --envmap
.../city.hdr`` scores against the ``city`` set by the file's stem.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from .assemble import View, make_scene, read_colour_stack, read_views
from .files import read_data_map, read_json
from .nerf import OPENGL_TO_OPENCV
from .scene import GroundTruth, Relit, SceneData
from .validate import check_c2w, check_K, check_size

NAME = "tensoir"
DESCRIPTION = "{split}_NNN/ folders each with metadata.json and rgba.png (TensoIR)"

METADATA = "metadata.json"
IMAGE = "rgba.png"
ALBEDO = "albedo.png"


def view_folders(root: Path, split: str) -> list[tuple[int, Path]]:
    """``(NNN, root/{split}_NNN)`` for every such folder holding a ``metadata.json``, in index order."""
    pattern = re.compile(rf"{re.escape(split)}_(\d+)$")
    found = []
    for p in root.iterdir() if root.is_dir() else ():
        m = pattern.match(p.name)
        if m and p.is_dir() and (p / METADATA).is_file():
            found.append((int(m.group(1)), p))
    return sorted(found)


def detect(root: Path, split: str) -> bool:
    return bool(view_folders(root, split))


def _number(meta: dict[str, Any], key: str, path: Path) -> float:
    value = meta.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"'{key}' must be a number, got {value!r}")
    return float(value)


def _camera(meta: dict[str, Any], path: Path, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(K, c2w)`` (OpenCV axes) of one view's ``metadata.json``, checked against its image's size."""
    w, h = _number(meta, "imw", path), _number(meta, "imh", path)
    if (int(w), int(h)) != (width, height):
        raise InputError(path, f"imw x imh is {int(w)}x{int(h)} but the view's {IMAGE} is {width}x{height}")
    angle = _number(meta, "cam_angle_x", path)
    if not 0.0 < angle < math.pi:
        raise InputError(path, f"'cam_angle_x' is {angle:g} radians; a field of view lies strictly between 0 and pi")
    raw = meta.get("cam_transform_mat")
    try:
        values = [float(v) for v in (raw.split(",") if isinstance(raw, str) else raw)]
    except (TypeError, ValueError):
        raise InputError(path, f"'cam_transform_mat' must be 16 comma-separated numbers, got {raw!r}") from None
    if len(values) != 16:
        raise InputError(path, f"'cam_transform_mat' must be 16 comma-separated numbers, got {len(values)}")
    c2w = check_c2w(np.array(values, np.float64).reshape(4, 4), path, "cam_transform_mat") @ OPENGL_TO_OPENCV
    f = 0.5 * width / math.tan(0.5 * angle)
    K = check_K(np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]]), path, "cam_angle_x")
    return K, c2w


def _albedo(folders: list[Path], size: tuple[int, int]) -> np.ndarray | None:
    files = [f / ALBEDO for f in folders]
    present = [p.is_file() for p in files]
    if not any(present):
        return None
    if not all(present):
        raise InputError(files[present.index(False)], "ground-truth albedo missing (other views have one)")
    maps = [read_data_map(p, 3, srgb=True) for p in files]
    for p, a in zip(files, maps):
        check_size(a.shape, p, size, "the views")
    return np.stack(maps)


def _relit(folders: list[Path], size: tuple[int, int]) -> list[Relit]:
    """A set per ``rgba_<env>.png`` that every test view has."""
    def names(folder: Path) -> set[str]:
        return {p.stem[len("rgba_"):] for p in folder.glob("rgba_*.png")}

    common = set.intersection(*(names(f) for f in folders))
    return [Relit(name=env, images=read_colour_stack([f / f"rgba_{env}.png" for f in folders], size), envmap=None)
            for env in sorted(common)]


def read(root: Path, split: str) -> SceneData:
    found = view_folders(root, split)
    if not found:
        raise InputError(root, f"no {split}_NNN/ folder with a {METADATA}")
    indices, folders = [i for i, _ in found], [f for _, f in found]
    views = []
    for f in folders:
        if not (f / IMAGE).is_file():
            raise InputError(f / IMAGE, "image file not found")
        views.append(View(image=f / IMAGE))
    stack = read_views(views)
    h, w = stack.images.shape[1:3]
    cams = [_camera(read_json(f / METADATA), f / METADATA, w, h) for f in folders]
    albedo = _albedo(folders, (h, w))
    gt = None
    if albedo is not None:
        gt = GroundTruth(albedo=torch.from_numpy(albedo),
                         mask=None if stack.masks is None else torch.from_numpy(stack.masks))
    return make_scene(
        root=root, split=split, fmt=NAME, views=views, stack=stack, K=[k for k, _ in cams], c2w=[c for _, c in cams],
        indices=indices, ground_truth=gt, relit=_relit(folders, (h, w)) if split == "test" else (),
    )
