"""PhySG / NeFII (official code) / NeRF++: ``cam_dict_norm.json`` with ``image/`` and ``mask/``.

    cam_dict_norm.json   {image name: {"K": 16 numbers (4x4, row-major), "W2C": 16 numbers
                         (world-to-camera 4x4, OpenCV axes), "img_size": [W, H] (optional)}}
    image/               the views, named as the json's keys (matched by name, or by stem)
    mask/                optional masks, same names or stems

The views are the json's entries in key order; images not named there are ignored. The world
frame is the json's own (already normalised to the unit sphere by the tools that write it).
PhySG keeps train and test views in ``train/`` and ``test/`` folders, each in this layout.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .files import IMAGE_SUFFIXES, matrix, read_json
from .scene import SceneData
from .validate import check_c2w, check_K
from .assemble import View, frame_indices, make_scene, read_views

NAME = "physg"
DESCRIPTION = "cam_dict_norm.json with image/ (PhySG, NeFII, NeRF++)"

JSON_NAME = "cam_dict_norm.json"


def detect(root: Path, split: str) -> bool:
    return (root / JSON_NAME).is_file() and (root / "image").is_dir()


def find_by_name(folder: Path, name: str) -> Path | None:
    """``folder/name`` if it exists, else the one image file in ``folder`` with the same stem."""
    exact = folder / name
    if exact.is_file():
        return exact
    stem = Path(name).stem if Path(name).suffix.lower() in IMAGE_SUFFIXES else name
    for suffix in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES):
        cand = folder / (stem + suffix)
        if cand.is_file():
            return cand
    return None


def read(root: Path, split: str) -> SceneData:
    path = root / JSON_NAME
    cams = read_json(path)
    if not cams:
        raise InputError(path, "no cameras in this file")
    has_masks = (root / "mask").is_dir()
    views, Ks, poses, sizes = [], [], [], []
    for name in sorted(cams):
        entry = cams[name]
        if not isinstance(entry, dict) or "K" not in entry or "W2C" not in entry:
            raise InputError(path, f"entry '{name}' lacks 'K' or 'W2C'")
        K = matrix(entry["K"], ((4, 4), (3, 3)), path, f"'{name}' K")[:3, :3]
        Ks.append(check_K(K, path, f"'{name}' K"))
        w2c = check_c2w(matrix(entry["W2C"], ((4, 4), (3, 4)), path, f"'{name}' W2C"), path, f"'{name}' W2C")
        c2w = np.eye(4)
        c2w[:3, :3] = w2c[:3, :3].T
        c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
        poses.append(c2w)
        sizes.append(entry.get("img_size"))
        image = find_by_name(root / "image", name)
        if image is None:
            raise InputError(root / "image" / name, f"image file not found (named in {JSON_NAME})")
        mask = None
        if has_masks:
            mask = find_by_name(root / "mask", image.name)
            if mask is None:
                raise InputError(root / "mask" / image.name, "mask file not found (mask/ holds masks for other views)")
        views.append(View(image=image, mask=mask))
    stack = read_views(views)
    h, w = stack.images.shape[1:3]
    for v, size in zip(views, sizes):
        if size is not None and list(size) != [w, h]:
            raise InputError(v.image, f"image is {w}x{h} but {JSON_NAME} gives img_size {size}")
    return make_scene(root=root, split=split, fmt=NAME, views=views, stack=stack, K=Ks, c2w=poses,
                      indices=frame_indices([v.image.stem for v in views]))
