"""COLMAP sparse models (binary or text), read with ``pycolmap`` (the optional extra ``nefii[colmap]``).

    sparse/0/ (or sparse/, or the folder itself)   cameras.bin|txt, images.bin|txt (+ points3D, rigs, frames)
    images/<name>                                  the images, by the model's image names
    masks/<name>.png or masks/<stem>.png           optional masks (COLMAP's own naming is <name>.png)

Views are the registered images in name order. COLMAP's pose is world-to-camera in OpenCV axes;
nefii inverts it and keeps COLMAP's world frame (arbitrary scale and orientation: nothing is
normalised). COLMAP puts pixel centres at +0.5, as nefii does, so ``K`` is taken as is.

Camera models: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are exact. ``SIMPLE_RADIAL``, ``RADIAL``,
``OPENCV`` and ``FULL_OPENCV`` with non-zero distortion are refused (undistort first with
``colmap image_undistorter``) unless ``allow_distortion=True``, which warns and keeps only
the pinhole part. Fisheye and other models are refused.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from .files import IMAGE_SUFFIXES
from .scene import SceneData
from .validate import check_c2w, check_K
from .assemble import View, make_scene, read_views

NAME = "colmap"
DESCRIPTION = "sparse/0/, sparse/ or ./ with cameras.bin|txt + images.bin|txt, and images/ (COLMAP)"

MODEL_DIRS = ("sparse/0", "sparse", ".")
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def _has(folder: Path, stem: str) -> bool:
    return (folder / f"{stem}.bin").is_file() or (folder / f"{stem}.txt").is_file()


def model_dir(root: Path) -> Path | None:
    """The first of ``sparse/0``, ``sparse``, ``.`` holding cameras and images files."""
    for d in MODEL_DIRS:
        p = (root / d) if d != "." else root
        if _has(p, "cameras") and _has(p, "images"):
            return p
    return None


def detect(root: Path, split: str) -> bool:
    return model_dir(root) is not None and (root / "images").is_dir()


def _import_pycolmap(where: Path):
    try:
        import pycolmap
    except ImportError:
        raise InputError(where, "reading COLMAP models needs pycolmap: pip install 'nefii[colmap]'") from None
    return pycolmap


def _mask_for(folder: Path, name: str) -> Path | None:
    stem = Path(name).with_suffix("").as_posix()
    for cand in [f"{name}.png", name] + [stem + s for s in IMAGE_SUFFIXES]:
        if (folder / cand).is_file():
            return folder / cand
    return None


def _intrinsics(cam, cameras_file: Path, allow_distortion: bool) -> np.ndarray:
    model = cam.model.name
    where = f"camera {cam.camera_id} ({model})"
    if model not in PINHOLE_MODELS + DISTORTED_MODELS:
        raise InputError(cameras_file, f"{where}: camera model not supported (nefii needs pinhole cameras; "
                                       "undistort with `colmap image_undistorter`)")
    extra = [float(cam.params[i]) for i in cam.extra_params_idxs()]
    if any(extra):
        names = cam.params_info.split(", ")[-len(extra):]
        values = ", ".join(f"{n}={v:.4g}" for n, v in zip(names, extra))
        if not allow_distortion:
            raise InputError(cameras_file, f"{where}: lens distortion ({values}) is not modelled by nefii; "
                                           "undistort with `colmap image_undistorter` first, "
                                           "or pass allow_distortion=True to ignore it")
        warnings.warn(f"{cameras_file}: {where}: ignoring lens distortion ({values})", stacklevel=3)
    K = np.array([[cam.focal_length_x, 0.0, cam.principal_point_x],
                  [0.0, cam.focal_length_y, cam.principal_point_y],
                  [0.0, 0.0, 1.0]])
    return check_K(K, cameras_file, where)


def read(root: Path, split: str, *, allow_distortion: bool = False) -> SceneData:
    mdir = model_dir(root)
    if mdir is None:
        raise InputError(root, "no COLMAP model (cameras.bin|txt and images.bin|txt) in sparse/0, sparse or here")
    pycolmap = _import_pycolmap(mdir)
    cameras_file = mdir / ("cameras.bin" if (mdir / "cameras.bin").is_file() else "cameras.txt")
    images_file = mdir / ("images.bin" if (mdir / "images.bin").is_file() else "images.txt")
    rec = pycolmap.Reconstruction()
    try:
        rec.read(str(mdir))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ check messages
        raise InputError(mdir, f"not a readable COLMAP model ({type(e).__name__}: {e})") from None
    registered = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not registered:
        raise InputError(images_file, "no registered (posed) images in this model")

    has_masks = (root / "masks").is_dir()
    views, Ks, poses = [], [], []
    for im in registered:
        cam = rec.cameras[im.camera_id]
        Ks.append(_intrinsics(cam, cameras_file, allow_distortion))
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        w2c = check_c2w(w2c, images_file, f"image '{im.name}'")
        c2w = np.eye(4)
        c2w[:3, :3] = w2c[:3, :3].T
        c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
        poses.append(c2w)
        image = root / "images" / im.name
        if not image.is_file():
            raise InputError(image, f"image file not found (named in {images_file.name})")
        mask = None
        if has_masks:
            mask = _mask_for(root / "masks", im.name)
            if mask is None:
                raise InputError(root / "masks" / f"{im.name}.png",
                                 "mask file not found (masks/ holds masks for other views)")
        views.append(View(image=image, mask=mask))
    stack = read_views(views)
    h, w = stack.images.shape[1:3]
    for v, im in zip(views, registered):
        cam = rec.cameras[im.camera_id]
        if (cam.width, cam.height) != (w, h):
            raise InputError(v.image, f"image is {w}x{h} but COLMAP camera {cam.camera_id} is {cam.width}x{cam.height}")
    return make_scene(root=root, split=split, fmt=NAME, views=views, stack=stack, K=Ks, c2w=poses,
                      indices=range(len(views)))
