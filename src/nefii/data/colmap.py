"""COLMAP sparse models (binary or text), read with ``pycolmap`` (the optional extra ``nefii[colmap]``).

    sparse/0/ (or sparse/, or the folder itself)   cameras.bin|txt, images.bin|txt (+ points3D, rigs, frames)
    images/<name>                                  the images, by the model's image names
    masks/<name>.png or masks/<stem>.png           optional masks (COLMAP's own naming is <name>.png)
    nefii_undistorted/                             written by nefii: undistorted images and masks (``undistort``)

Views are the registered images in name order. COLMAP's pose is world-to-camera in OpenCV axes;
nefii inverts it and keeps COLMAP's world frame (arbitrary scale and orientation: nothing is
normalised). COLMAP puts pixel centres at +0.5, as nefii does, so ``K`` is taken as is.

Camera models: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are read as they are. Distorted cameras are
undistorted once with OpenCV into ``nefii_undistorted/`` (keyed by the cameras file and the
images) and read from there with the pinhole ``K`` OpenCV chose, as the nerfstudio reader does:
``SIMPLE_RADIAL`` (``k``), ``RADIAL`` (``k1, k2``), ``OPENCV`` (``k1, k2, p1, p2``) and
``FULL_OPENCV`` (``k1, k2, p1, p2, k3``) are OpenCV's Brown-Conrady lens, ``OPENCV_FISHEYE``
(``k1..k4``) its fisheye. ``FULL_OPENCV``'s rational terms (non-zero ``k4, k5, k6``) and other
models (``FOV``, the other fisheyes, ...) are refused: undistort with ``colmap image_undistorter``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .files import IMAGE_SUFFIXES
from .scene import SceneData
from .undistort import COEFFS, Lens, pinhole_views
from .validate import check_c2w, check_K
from .assemble import View, make_scene, read_exposures, read_views

NAME = "colmap"
DESCRIPTION = "sparse/0/, sparse/ or ./ with cameras.bin|txt + images.bin|txt, and images/ (COLMAP)"

MODEL_DIRS = ("sparse/0", "sparse", ".")
LENS_MODELS: dict[str, str] = {"SIMPLE_PINHOLE": "PINHOLE", "PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV",
                               "RADIAL": "OPENCV", "OPENCV": "OPENCV", "FULL_OPENCV": "OPENCV",
                               "OPENCV_FISHEYE": "OPENCV_FISHEYE"}
"""each COLMAP camera model nefii reads, and the ``undistort.Lens`` model it is"""
OPENCV_NAMES = {"k": "k1"}
"""COLMAP coefficient names that OpenCV spells otherwise (SIMPLE_RADIAL's ``k``); the others agree"""


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


def lens_of(cam, cameras_file: Path) -> Lens:
    """A COLMAP camera as a :class:`Lens`: its pinhole part, and its coefficients by OpenCV's names."""
    model = cam.model.name
    where = f"camera {cam.camera_id} ({model})"
    if model not in LENS_MODELS:
        raise InputError(cameras_file, f"{where}: camera model not supported (nefii reads {', '.join(LENS_MODELS)}; "
                                       "undistort with `colmap image_undistorter`)")
    lens_model = LENS_MODELS[model]
    names = cam.params_info.split(", ")
    coeffs = {OPENCV_NAMES.get(names[i], names[i]): float(cam.params[i]) for i in cam.extra_params_idxs()}
    rational = {n: v for n, v in coeffs.items() if n not in COEFFS[lens_model] and v != 0.0}  # FULL_OPENCV's k4..k6
    if rational:
        values = ", ".join(f"{n}={v:.4g}" for n, v in rational.items())
        raise InputError(cameras_file, f"{where}: rational distortion terms ({values}) are not supported; "
                                       "undistort with `colmap image_undistorter` first")
    K = np.array([[cam.focal_length_x, 0.0, cam.principal_point_x],
                  [0.0, cam.focal_length_y, cam.principal_point_y],
                  [0.0, 0.0, 1.0]])
    return Lens(model=lens_model, K=check_K(K, cameras_file, where),
                coeffs=tuple(coeffs.get(n, 0.0) for n in COEFFS[lens_model]),
                width=int(cam.width), height=int(cam.height))


def read(root: Path, split: str) -> SceneData:
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

    by_camera = {cid: lens_of(rec.cameras[cid], cameras_file) for cid in sorted({im.camera_id for im in registered})}
    lenses = [by_camera[im.camera_id] for im in registered]
    has_masks = (root / "masks").is_dir()
    views, poses = [], []
    for im in registered:
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

    # ---- undistort every distorted view (every read of this model shares the cache)
    exposure = read_exposures(views)
    sources, Ks = pinhole_views(root, cameras_file, views, lenses)

    stack = read_views(sources, exposure)
    h, w = stack.images.shape[1:3]
    for v, im in zip(views, registered):
        cam = rec.cameras[im.camera_id]
        if (cam.width, cam.height) != (w, h):
            raise InputError(v.image, f"image is {w}x{h} but COLMAP camera {cam.camera_id} is {cam.width}x{cam.height}")
    return make_scene(root=root, split=split, fmt=NAME, views=views, stack=stack, K=Ks, c2w=poses,
                      indices=range(len(views)))
