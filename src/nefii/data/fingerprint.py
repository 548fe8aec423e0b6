"""What a run was fitted on, as content hashes: a resume on other data is refused by comparing them.

The cameras (poses, intrinsics, image size, as loaded, so any camera file format hashes alike), the training
images and the mesh file. Paths are recorded too, but a dataset that moved keeps its fingerprint.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .scene import Cameras, SceneData


@dataclass(frozen=True)
class DataFingerprint:
    path: str
    """the dataset folder (absolute), for the messages"""
    cameras: str
    """sha256 of the poses, intrinsics and image size"""
    images: str
    """sha256 of the training images"""
    mesh: str | None
    """sha256 of the frozen geometry's mesh file (None: none was used)"""

    def differences(self, other: DataFingerprint) -> list[str]:
        """The parts whose content differs (``cameras``, ``images``, ``mesh``)."""
        return [name for name in ("cameras", "images", "mesh") if getattr(self, name) != getattr(other, name)]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: Any, where: Path) -> DataFingerprint:
        names = [f.name for f in fields(DataFingerprint)]
        if not isinstance(d, dict) or set(d) != set(names) or not all(isinstance(d[n], (str, type(None))) for n in names):
            raise InputError(where, "malformed 'data' record")
        return DataFingerprint(**d)


def require_same(recorded: DataFingerprint, found: DataFingerprint, run: Path) -> None:
    """Refuse to continue ``run``, fitted on ``recorded``, on ``found`` when their contents differ."""
    diff = recorded.differences(found)
    if diff:
        raise InputError(found.path, f"--resume on other data: {run} was fitted on {recorded.path}, and the "
                                     f"{', '.join(diff)} differ; use another --out for this data")


def arrays_sha256(*arrays: np.ndarray) -> str:
    """sha256 of the arrays' dtypes, shapes and values, in order."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    return h.hexdigest()


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError as e:
        raise InputError(path, f"cannot read ({e.strerror})") from None
    return h.hexdigest()


def cameras_sha256(cams: Cameras) -> str:
    """sha256 of the cameras' poses, intrinsics and image size."""
    return arrays_sha256(cams.c2w.double().numpy(), cams.K.double().numpy(), np.array([cams.height, cams.width]))


def fingerprint(scene: SceneData, mesh: Path | None) -> DataFingerprint:
    """The fingerprint of ``scene`` (its training split) fitted on ``mesh``."""
    return DataFingerprint(str(Path(scene.root).resolve()), cameras_sha256(scene.cameras),
                           arrays_sha256(scene.images.numpy()), None if mesh is None else file_sha256(mesh))
