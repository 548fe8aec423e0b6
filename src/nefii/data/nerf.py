"""nefii's own layout (what ``nefii synth`` writes, docs/datasets.md) and plain NeRF-synthetic.

    transforms_{split}.json   camera_angle_x, optional fl_x fl_y cx cy w h (top level or per frame),
                              frames: file_path (with or without suffix), transform_matrix
                              (camera-to-world, OpenGL/Blender axes)
    {split}/r_K.exr|png       the image; an .exr is preferred to a .png of the same stem
    {split}/r_K_mask.png      optional mask (else alpha > 0.5)
    {split}/r_K_{albedo,roughness,specular,diffuse,normal,depth}.exr   optional ground truth
    relight/<env>/r_K.exr, relight/<env>.exr    optional: test views under other lights
    mesh.ply, envmap.exr      optional ground-truth geometry and lighting

Poses are converted to OpenCV axes (``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``); the world frame
is kept as is. Without ``fl_x``, ``fx = fy = W / (2 tan(camera_angle_x / 2))`` and the principal
point is the image centre (``camera_angle_y``, if given, sets ``fy``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..errors import InputError
from .files import IMAGE_SUFFIXES, matrix, read_data_map, read_json, resolve_image
from .scene import GroundTruth, Relit, SceneData
from .validate import check_c2w, check_K, check_size
from .assemble import View, ViewStack, make_scene, read_colour_stack, read_views

NAME = "nerf"
DESCRIPTION = "transforms_{split}.json with {split}/ images (nefii layout, NeRF-synthetic)"

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""``c2w_cv = c2w_gl @ OPENGL_TO_OPENCV`` (numpy twin of ``nefii.camera.OPENGL_TO_OPENCV``)"""

GT_CHANNELS = {"albedo": 3, "roughness": 1, "specular": 3, "diffuse": 3, "normal": 3, "depth": 1}
"""ground-truth maps ``r_K_<kind>.exr`` and their channel counts"""


def detect(root: Path, split: str) -> bool:
    return (root / f"transforms_{split}.json").is_file()


def frames_of(meta: dict[str, Any], path: Path) -> list[dict[str, Any]]:
    """The non-empty list of frames, each with ``file_path`` and ``transform_matrix``."""
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(path, "no 'frames' list (or it is empty)")
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or not isinstance(f.get("file_path"), str) or "transform_matrix" not in f:
            raise InputError(path, f"frame {i} lacks 'file_path' (a string) or 'transform_matrix'")
    return frames


def number(value: Any, path: Path, where: str, key: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(path, f"{where}: '{key}' is not a number ({value!r})") from None
    if not math.isfinite(x):
        raise InputError(path, f"{where}: '{key}' is not finite ({value!r})")
    return x


def frame_number(meta: dict[str, Any], frame: dict[str, Any], key: str, path: Path, where: str) -> float | None:
    """The frame's number ``key``, else the top level's (nerfstudio's per-frame override); ``None`` if neither
    has it."""
    v = frame.get(key, meta.get(key))
    return None if v is None else number(v, path, where, key)


def intrinsics(meta: dict[str, Any], frame: dict[str, Any], width: int, height: int,
               path: Path, where: str) -> np.ndarray:
    """``K`` from a frame's keys, falling back to the top level's (nerfstudio's per-frame override)."""
    def get(key: str) -> float | None:
        return frame_number(meta, frame, key, path, where)

    def angle(key: str) -> float | None:
        a = get(key)
        if a is not None and not 0.0 < a < math.pi:
            raise InputError(path, f"{where}: '{key}' is {a:g} radians; a field of view lies strictly between 0 "
                                   "and pi")
        return a

    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        angle_x = angle("camera_angle_x")
        if angle_x is None:
            raise InputError(path, f"{where}: no intrinsics ('fl_x' or 'camera_angle_x')")
        fx = 0.5 * width / math.tan(0.5 * angle_x)
        angle_y = angle("camera_angle_y")
        if fy is None and angle_y is not None:
            fy = 0.5 * height / math.tan(0.5 * angle_y)
    fy = fx if fy is None else fy
    cx, cy = get("cx"), get("cy")
    K = np.array([[fx, 0.0, 0.5 * width if cx is None else cx],
                  [0.0, fy, 0.5 * height if cy is None else cy],
                  [0.0, 0.0, 1.0]])
    return check_K(K, path, where)


def gl_pose(frame: dict[str, Any], path: Path, where: str) -> np.ndarray:
    """The frame's ``transform_matrix`` (OpenGL camera-to-world) checked, as OpenCV camera-to-world."""
    m = matrix(frame["transform_matrix"], ((4, 4), (3, 4)), path, where)
    return check_c2w(m, path, where) @ OPENGL_TO_OPENCV


def _stem(image: Path) -> Path:
    return image.with_suffix("")


def mask_beside(image: Path) -> Path | None:
    """nefii's optional ``r_K_mask.png`` beside ``r_K.exr``, if it is there."""
    mask = _stem(image).with_name(_stem(image).name + "_mask.png")
    return mask if mask.is_file() else None


@dataclass(frozen=True)
class Frames:
    """The views a NeRF-style frame list names, read and checked."""

    views: list[View]
    stack: ViewStack
    K: list[np.ndarray]
    """``(3, 3)`` per view"""
    c2w: list[np.ndarray]
    """``(4, 4)`` OpenCV camera-to-world per view"""


def read_frames(path: Path, meta: dict[str, Any], frames: Sequence[dict[str, Any]], folders: Sequence[Path],
                mask_of: Callable[[Path], Path | None], prefer: tuple[str, ...] = IMAGE_SUFFIXES,
                numbers: Sequence[int] | None = None) -> Frames:
    """Read the frames of ``path`` (a transforms json whose top level is ``meta``): each frame's pose, its image
    ``folder / file_path`` (suffix resolved in ``prefer`` order), the mask file ``mask_of(image)`` names
    (``None``: none), and ``K`` from the frame's keys or the top level's. ``numbers``: the frames' positions
    in the file, for messages (default ``0..N-1``)."""
    numbers = range(len(frames)) if numbers is None else numbers
    where = [f"frame {i} ({f['file_path']})" for i, f in zip(numbers, frames)]
    poses = [gl_pose(f, path, wh) for f, wh in zip(frames, where)]
    views = []
    for f, folder in zip(frames, folders):
        image = resolve_image(folder / f["file_path"], prefer)
        views.append(View(image=image, mask=mask_of(image)))
    stack = read_views(views)
    h, w = stack.images.shape[1:3]
    if "w" in meta or "h" in meta:
        jw, jh = meta.get("w", w), meta.get("h", h)
        if (jw, jh) != (w, h):
            raise InputError(views[0].image, f"image is {w}x{h} but {path.name} gives w={jw}, h={jh}")
    Ks = [intrinsics(meta, f, w, h, path, wh) for f, wh in zip(frames, where)]
    return Frames(views, stack, Ks, poses)


def _ground_truth(stems: list[Path], size: tuple[int, int], masks: np.ndarray | None,
                  mask_files: bool) -> GroundTruth | None:
    maps: dict[str, torch.Tensor] = {}
    for kind, channels in GT_CHANNELS.items():
        files = [s.with_name(f"{s.name}_{kind}.exr") for s in stems]
        present = [f.is_file() for f in files]
        if not any(present):
            continue
        if not all(present):
            missing = files[present.index(False)]
            raise InputError(missing, f"ground-truth {kind} map missing (other views have one)")
        arrs = [read_data_map(f, channels) for f in files]
        for f, a in zip(files, arrs):
            check_size(a.shape, f, size, "the views")
        stacked = np.stack(arrs)
        maps[kind] = torch.from_numpy(stacked[..., 0] if channels == 1 else stacked)
    if mask_files and masks is not None:
        maps["mask"] = torch.from_numpy(masks)
    return GroundTruth(**maps) if maps else None


def _relit(root: Path, stems: list[Path], size: tuple[int, int], prefer: tuple[str, ...]) -> list[Relit]:
    folder = root / "relight"
    if not folder.is_dir():
        return []
    out = []
    for env_dir in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        images = read_colour_stack([resolve_image(env_dir / s.name, prefer) for s in stems], size)
        env_file = next((p for p in (folder / f"{env_dir.name}.exr", env_dir / "envmap.exr") if p.is_file()), None)
        env = None if env_file is None else torch.from_numpy(read_data_map(env_file, 3))
        out.append(Relit(name=env_dir.name, images=images, envmap=env))
    return out


def read(root: Path, split: str, *, prefer: tuple[str, ...] = IMAGE_SUFFIXES) -> SceneData:
    """Read one split; ``prefer`` orders the suffixes tried for each frame's image."""
    path = root / f"transforms_{split}.json"
    meta = read_json(path)
    frames = frames_of(meta, path)
    got = read_frames(path, meta, frames, [root] * len(frames), mask_beside, prefer)
    views, stack = got.views, got.stack
    h, w = stack.images.shape[1:3]
    stems = [_stem(v.image) for v in views]
    mask_files = all(v.mask is not None for v in views)
    envmap_file = root / "envmap.exr"
    mesh = root / "mesh.ply"
    return make_scene(
        root=root, split=split, fmt=NAME, views=views, stack=stack, K=got.K, c2w=got.c2w,
        ground_truth=_ground_truth(stems, (h, w), stack.masks, mask_files),
        mesh_path=mesh if mesh.is_file() else None,
        envmap=read_data_map(envmap_file, 3) if envmap_file.is_file() else None,
        relit=_relit(root, stems, (h, w), prefer) if split == "test" else (),
    )
