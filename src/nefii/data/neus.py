"""NeuS / IDR / VolSDF: ``cameras_sphere.npz`` (or ``cameras.npz``) with ``image/`` and ``mask/``.

    cameras_sphere.npz   world_mat_K: projection ``K [R | t]`` (4x4 or 3x4) from the dataset's world
                         to pixels, OpenCV axes; scale_mat_K: similarity from the normalised frame
                         (object inside the unit sphere) to the dataset's world
    image/               the views, in file-name order: view K is the K-th file
    mask/                optional masks, same order

World frame: the **normalised** one NeuS trains in. ``P = world_mat @ scale_mat`` is split into
``K`` and the pose by an RQ decomposition (what NeuS's ``load_K_Rt_from_P`` does with
``cv2.decomposeProjectionMatrix``); ``scene_to_source = scale_mat`` maps nefii's world back to the
dataset's. ``K`` keeps any skew the decomposition finds; nefii's ray generation ignores skew, so a
skew above 1e-3 fx warns. A missing ``scale_mat_K`` counts as the identity.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import scipy.linalg

from ..errors import InputError
from .files import list_images, matrix, read_npz
from .scene import SceneData
from .validate import check_c2w, check_K
from .assemble import View, make_scene, read_views

NAME = "neus"
DESCRIPTION = "cameras_sphere.npz or cameras.npz with image/ (NeuS, IDR)"

NPZ_NAMES = ("cameras_sphere.npz", "cameras.npz")


def detect(root: Path, split: str) -> bool:
    return (root / "image").is_dir() and any((root / n).is_file() for n in NPZ_NAMES)


def decompose_projection(P: np.ndarray, path: Path, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``P = K [R | t]`` (3x4) -> (``K`` with positive diagonal and ``K[2, 2] = 1``, OpenCV camera-to-world).

    ``P`` and ``-P`` are the same camera; the sign giving ``det R = +1`` is taken.
    """
    if not np.isfinite(P).all():
        raise InputError(path, f"{where}: NaN or infinite entries")
    M, p4 = P[:, :3], P[:, 3]
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[-1] <= 1e-12 * sv[0]:
        raise InputError(path, f"{where}: singular projection matrix (its 3x3 part has rank < 3)")
    K, R = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R  # D @ D = I, so K R is unchanged
    if np.linalg.det(R) < 0:
        R = -R
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = -np.linalg.solve(M, p4)  # camera centre: the null vector of P
    return K / K[2, 2], c2w


def _scale_mat(arrays: dict[str, np.ndarray], i: int, path: Path) -> np.ndarray:
    key = f"scale_mat_{i}"
    if key not in arrays:
        return np.eye(4)
    S = matrix(arrays[key], ((4, 4),), path, key)
    A = S[:3, :3]
    s2 = np.trace(A.T @ A) / 3.0
    if not np.isfinite(S).all() or s2 <= 0 or not np.allclose(A.T @ A, s2 * np.eye(3), rtol=1e-6, atol=1e-9 * s2) \
            or not np.allclose(S[3], [0, 0, 0, 1]):
        raise InputError(path, f"{key} is not a similarity (uniform scale, rotation, translation)")
    return S


def read(root: Path, split: str) -> SceneData:
    path = next(root / n for n in NPZ_NAMES if (root / n).is_file())
    images = list_images(root / "image")
    if not images:
        raise InputError(root / "image", "no images (.png, .jpg, .exr) in this folder")
    masks = list_images(root / "mask") if (root / "mask").is_dir() else []
    if masks and len(masks) != len(images):
        raise InputError(root / "mask", f"{len(masks)} masks for {len(images)} images in image/")
    arrays = read_npz(path)

    Ks, poses = [], []
    scale0 = _scale_mat(arrays, 0, path)
    for i, img in enumerate(images):
        key = f"world_mat_{i}"
        if key not in arrays:
            raise InputError(path, f"no '{key}' for image/{img.name}")
        W = matrix(arrays[key], ((4, 4), (3, 4)), path, key)[:3, :4]
        S = _scale_mat(arrays, i, path)
        if not np.allclose(S, scale0, rtol=1e-6, atol=1e-9):
            raise InputError(path, f"scale_mat_{i} differs from scale_mat_0; nefii needs one world frame")
        K, c2w = decompose_projection(W @ S, path, key)
        if abs(K[0, 1]) > 1e-3 * K[0, 0]:
            warnings.warn(f"{path}: {key} has pixel skew {K[0, 1]:.3g}; nefii's rays ignore skew", stacklevel=2)
        Ks.append(check_K(K, path, key))
        poses.append(check_c2w(c2w, path, key))

    views = [View(image=img, mask=masks[i] if masks else None) for i, img in enumerate(images)]
    stack = read_views(views)
    return make_scene(root=root, split=split, fmt=NAME, views=views, stack=stack, K=Ks, c2w=poses,
                      indices=range(len(views)), scene_to_source=scale0)
