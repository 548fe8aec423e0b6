"""Stanford-ORB's blender layout (Kuang et al., NeurIPS 2023 Datasets and Benchmarks), read as it ships.

    <data>/blender_HDR/<scene>/                 (blender_LDR: the same with 8-bit sRGB .png images)
        transforms_{train,test}.json            NeRF-synthetic: camera_angle_x; frames: file_path
                                                (``./train/0000``, no suffix), transform_matrix (OpenGL c2w)
        {train,test}/NNNN.exr                   linear HDR photographs
        {train,test}_mask/NNNN.png              every view's mask (white = object)
        transforms_novel.json                   the object's test photographs from its other scenes; per
                                                frame: scene_name (that capture's folder, beside this one),
                                                file_path (inside it), transform_matrix (already aligned to
                                                this scene's world), camera_angle_x
    <data>/ground_truth/<scene>/
        env_map/NNNN.exr                        the environment of test photograph NNNN, in its camera's frame
        mesh_blender/mesh.obj                   the scanned object, in this scene's world

Frames, cameras and intrinsics go through the ``nerf`` reader's helpers (OpenGL -> OpenCV; per-frame
``camera_angle_x`` as ``transforms_novel.json`` has it). The test split's ``relit`` holds one
:class:`Relit` per capture scene named in ``transforms_novel.json`` (in order of first appearance):
its photographs, masks and cameras, and each photograph's own environment map turned into this
scene's world and nefii's mapping (:func:`camera_envmap_to_world`). ``mesh_path`` is the scan.
The pseudo ground truth of ``ground_truth/`` (normals, depth, albedo ``.npy``) and the test split's own
environment maps are not read.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..render.equirect import pixel_directions
from .assemble import frame_indices, make_scene
from .files import IMAGE_SUFFIXES, read_data_map, read_json
from .nerf import Frames, frames_of, read_frames
from .scene import Cameras, Relit, SceneData
from .validate import check_size

NAME = "stanford_orb"
DESCRIPTION = "transforms_{split}.json with {split}/ images and {split}_mask/ masks (Stanford-ORB blender_HDR|LDR)"

NOVEL = "transforms_novel.json"
"""the test photographs of the object's other capture scenes (other lights)"""


def detect(root: Path, split: str) -> bool:
    return (root / f"transforms_{split}.json").is_file() and (root / f"{split}_mask").is_dir()


def mask_path(image: Path) -> Path:
    """``<dir>_mask/<stem>.png`` for ``<dir>/<stem>.exr|png``: where every Stanford-ORB view has its mask."""
    return image.parent.with_name(image.parent.name + "_mask") / f"{image.stem}.png"


def ground_truth_root(root: Path) -> Path:
    """``<data>/ground_truth`` for a scene folder ``<data>/blender_HDR|LDR/<scene>``."""
    return root.resolve().parent.parent / "ground_truth"


def ground_truth_folder(root: Path, scene: str) -> Path:
    """``<data>/ground_truth/<scene>``."""
    return ground_truth_root(root) / scene


# --------------------------------------------------------------------------- environment maps


def camera_uv(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stanford-ORB's lat-long mapping of a direction in the photograph's camera frame (OpenCV axes: x right,
    y down, z forward) -> ``(u, v)`` in [0, 1]:

        u = (atan2(x, z) + pi) / (2 pi)     forward at u = 0.5, right at 0.75, left at 0.25, behind at the seam
        v = acos(-y) / pi                   row 0 is the camera's up

    (``orb/utils/env_map.py`` writes it in Blender camera axes: ``atan2(x, -z)``, ``acos(y)``.)"""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    u = (np.arctan2(x, z) + math.pi) / (2.0 * math.pi)
    v = np.arctan2(np.hypot(x, z), -y) / math.pi
    return u, v


def _bilinear(image: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """``image`` at continuous ``(row, col)`` with integer texel centres, bilinear, clamped to the edges."""
    h, w = image.shape[:2]
    r0 = np.clip(np.floor(row), 0, h - 2).astype(np.int64)
    c0 = np.clip(np.floor(col), 0, w - 2).astype(np.int64)
    fr = np.clip(row - r0, 0.0, 1.0)[..., None]
    fc = np.clip(col - c0, 0.0, 1.0)[..., None]
    top = image[r0, c0] * (1 - fc) + image[r0, c0 + 1] * fc
    bottom = image[r0 + 1, c0] * (1 - fc) + image[r0 + 1, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def camera_envmap_to_world(image: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """A Stanford-ORB environment map (``(h, w, 3)``, in the frame of the camera ``c2w``, OpenCV
    camera-to-world) -> the same light as an ``(h, w, 3)`` map of the world in nefii's mapping.

    Each nefii texel centre (:func:`nefii.render.equirect.pixel_directions`) is turned into the camera's
    frame and looked up in :func:`camera_uv`, bilinearly on Stanford-ORB's grid: texel ``(i, j)`` sits at
    ``(u, v) = (j / (w - 1), i / (h - 1))``, from pole to pole and seam to seam (Mitsuba's envmap grid,
    which ``orb/utils/env_map.py`` also uses)."""
    h, w = image.shape[:2]
    d_world = pixel_directions(h, w, dtype=torch.float64).numpy()
    d_cam = d_world @ c2w[:3, :3]                     # R^T d for each row vector d
    u, v = camera_uv(d_cam)
    src = np.asarray(image, np.float64)
    return _bilinear(src, v * (h - 1), u * (w - 1)).astype(np.float32)


def _view_envmaps(folder: Path, got: Frames) -> np.ndarray:
    """``(N, He, We, 3)``: each photograph's ``env_map/<stem>.exr`` in world frame and nefii's mapping."""
    maps: list[np.ndarray] = []
    first: Path | None = None
    for view, c2w in zip(got.views, got.c2w):
        f = folder / f"{view.image.stem}.exr"
        if not f.is_file():
            raise InputError(f, f"environment map not found (Stanford-ORB has one per test photograph; this one "
                                f"lights {view.image})")
        img = read_data_map(f, 3)
        h, w = img.shape[:2]
        if h < 2 or w < 2:
            raise InputError(f, f"environment map of {w}x{h} pixels is too small to look up")
        if not (img > 0).any():
            raise InputError(f, "environment map is black everywhere: nothing to light with")
        if first is None:
            first = f
        else:
            check_size(img.shape, f, maps[0].shape[:2], first)
        maps.append(camera_envmap_to_world(img, c2w))
    return np.stack(maps)


# --------------------------------------------------------------------------- reading


def _scene_name(frame: dict[str, Any], i: int, path: Path) -> str:
    name = frame.get("scene_name")
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
        raise InputError(path, f"frame {i} ({frame['file_path']}): 'scene_name' (the capture folder the "
                               f"photograph is in) is missing or not a folder name: {name!r}")
    return name


def _novel(root: Path, path: Path, prefer: tuple[str, ...]) -> list[Relit]:
    """One :class:`Relit` per capture scene of ``transforms_novel.json``."""
    meta = read_json(path)
    frames = frames_of(meta, path)
    groups: dict[str, list[int]] = {}
    for i, f in enumerate(frames):
        groups.setdefault(_scene_name(f, i, path), []).append(i)
    out = []
    for name, numbers in groups.items():
        folder = root.resolve().parent / name
        if not folder.is_dir():
            raise InputError(folder, f"capture folder not found ({path.name} frame {numbers[0]} has scene_name "
                                     f"'{name}')")
        sub = [frames[i] for i in numbers]
        got = read_frames(path, meta, sub, [folder] * len(sub), mask_path, prefer, numbers=numbers)
        h, w = got.stack.images.shape[1:3]
        out.append(Relit(
            name=name, images=torch.from_numpy(np.ascontiguousarray(got.stack.images, dtype=np.float32)),
            envmap=None,
            view_envmaps=torch.from_numpy(_view_envmaps(ground_truth_folder(root, name) / "env_map", got)),
            cameras=Cameras(K=torch.from_numpy(np.stack(got.K)), c2w=torch.from_numpy(np.stack(got.c2w)),
                            height=int(h), width=int(w)),
            masks=torch.from_numpy(got.stack.masks),
            indices=frame_indices([v.image.name.split(".")[0] for v in got.views])))
    return out


def _relit(root: Path, prefer: tuple[str, ...]) -> list[Relit]:
    """The test split's novel-light sets; none without ``transforms_novel.json``, and none (with a warning)
    without the ``ground_truth`` folder their maps are in (it may be downloaded apart)."""
    novel = root / NOVEL
    if not novel.is_file():
        return []
    maps = ground_truth_root(root)
    if not maps.is_dir():
        warnings.warn(f"{novel}: no {maps} (Stanford-ORB's ground_truth folder, with the maps of the novel-light "
                      "photographs): those photographs are not read", stacklevel=3)
        return []
    return _novel(root, novel, prefer)


def read(root: Path, split: str, *, prefer: tuple[str, ...] = IMAGE_SUFFIXES) -> SceneData:
    """Read one split; ``prefer`` orders the suffixes tried for each frame's image (``.exr`` first)."""
    path = root / f"transforms_{split}.json"
    meta = read_json(path)
    frames = frames_of(meta, path)
    got = read_frames(path, meta, frames, [root] * len(frames), mask_path, prefer)
    mesh = ground_truth_folder(root, root.resolve().name) / "mesh_blender" / "mesh.obj"
    return make_scene(root=root, split=split, fmt=NAME, views=got.views, stack=got.stack, K=got.K, c2w=got.c2w,
                      mesh_path=mesh if mesh.is_file() else None,
                      relit=_relit(root, prefer) if split == "test" else ())
