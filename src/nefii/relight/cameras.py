"""The cameras to relight: a dataset's test views, or any NeRF-style ``transforms.json`` (``--cameras``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data.files import read_image, read_json, resolve_image
from ..data.nerf import frames_of, gl_pose, intrinsics
from ..data.scene import Cameras
from ..data.assemble import frame_indices
from ..config_tools import machine_memory_bytes
from ..errors import InputError


@dataclass(frozen=True)
class Views:
    cameras: Cameras
    indices: tuple[int, ...]
    """output names: the ``K`` of each frame's ``r_K`` (else its position)"""


BYTES_PER_PIXEL = 128
"""what a rendered view holds per pixel: the accumulators, the RGBA result, the EXR and PNG being written"""


def _size(meta: dict, path: Path, frames: list[dict]) -> tuple[int, int]:
    """``(w, h)`` from the file, else from the first frame's image."""
    w, h = meta.get("w"), meta.get("h")
    if w is None or h is None:
        try:
            image = resolve_image(path.parent / frames[0]["file_path"])
        except InputError:
            raise InputError(path, "has no 'w' and 'h' (image size in pixels) and its first frame's image "
                                   "is not there to read them from") from None
        h, w = read_image(image).rgb.shape[:2]
    if not all(isinstance(v, (int, float)) and float(v).is_integer() and v > 0 for v in (w, h)):
        raise InputError(path, f"'w' and 'h' must be positive whole numbers, got w={w!r}, h={h!r}")
    need, have = BYTES_PER_PIXEL * float(w) * float(h), machine_memory_bytes()
    if need > have:
        raise InputError(path, f"{int(w)}x{int(h)} pixels would need about {need / 2**30:.0f} GiB for one view's "
                               f"image buffers, more than this machine's {have / 2**30:.0f} GiB")
    return int(w), int(h)


def views_from_transforms(path: str | Path) -> Views:
    """Cameras of a ``transforms.json`` (OpenGL/Blender poses, converted to OpenCV as the nerf reader does)."""
    path = Path(path)
    meta = read_json(path)
    frames = frames_of(meta, path)
    w, h = _size(meta, path, frames)
    where = [f"frame {i} ({f['file_path']})" for i, f in enumerate(frames)]
    poses = np.stack([gl_pose(f, path, wh) for f, wh in zip(frames, where)])
    Ks = np.stack([intrinsics(meta, f, w, h, path, wh) for f, wh in zip(frames, where)])
    cams = Cameras(K=torch.from_numpy(Ks), c2w=torch.from_numpy(poses), height=h, width=w)
    return Views(cams, frame_indices([Path(f["file_path"]).name.split(".")[0] for f in frames]))
