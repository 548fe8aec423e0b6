"""Camera rigs for synthetic scenes: pinholes on a band of a sphere, looking at the origin.

Train and test views are interleaved on one Fibonacci spiral over the band of elevations
(uniform in solid angle), so both splits cover it evenly and never share a pose; the
spiral's starting azimuth comes from the seed. Poses are built as OpenCV camera-to-world
matrices (nefii's internal convention) and handed out in OpenGL/Blender axes, as the
NeRF-synthetic ``transforms_*.json`` files store them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..camera import OPENGL_TO_OPENCV, look_at

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class Rig:
    fov_x: float
    """horizontal field of view, radians (square pixels, principal point at the centre)"""
    width: int
    height: int
    distance: float
    train: np.ndarray
    """(N, 4, 4) camera-to-world, OpenGL axes (x right, y up, looking down -z)"""
    test: np.ndarray
    """(M, 4, 4) likewise"""

    @property
    def focal(self) -> float:
        return 0.5 * self.width / math.tan(0.5 * self.fov_x)


def band_directions(n: int, elevation_deg: tuple[float, float], azimuth0: float) -> np.ndarray:
    """``n`` unit vectors on a Fibonacci spiral between two elevations, ordered by height."""
    z0, z1 = (math.sin(math.radians(e)) for e in elevation_deg)
    z = z0 + (np.arange(n) + 0.5) / n * (z1 - z0)
    phi = azimuth0 + GOLDEN_ANGLE * np.arange(n)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def split_indices(n_train: int, n_test: int) -> tuple[np.ndarray, np.ndarray]:
    """Spread ``n_test`` indices evenly over ``n_train + n_test``; the rest are training views."""
    n = n_train + n_test
    test = np.floor((np.arange(n_test) + 0.5) * n / n_test).astype(np.int64)
    train = np.setdiff1d(np.arange(n), test)
    return train, test


def c2w_gl_looking_at_origin(eye: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world of a camera at ``eye`` looking at the origin, world Z up."""
    e = torch.as_tensor(eye, dtype=torch.float64)
    c2w_cv = look_at(e, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return (c2w_cv @ OPENGL_TO_OPENCV).numpy()


def make_rig(n_train: int, n_test: int, res: int, radius: float, elevation_deg: tuple[float, float],
             seed: int, fov_x_deg: float = 40.0, margin: float = 1.08) -> Rig:
    """Cameras at a distance where the bounding sphere of ``radius`` fills the view up to ``margin``."""
    fov = math.radians(fov_x_deg)
    distance = margin * radius / math.sin(0.5 * fov)
    azimuth0 = float(np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi))
    dirs = band_directions(n_train + n_test, elevation_deg, azimuth0)
    train, test = split_indices(n_train, n_test)
    poses = np.stack([c2w_gl_looking_at_origin(distance * d) for d in dirs])
    return Rig(fov, res, res, distance, poses[train], poses[test])


def transforms_json(rig: Rig, poses: np.ndarray, split: str) -> dict:
    """The NeRF-synthetic ``transforms_<split>.json`` content (``file_path`` without extension)."""
    return {
        "camera_angle_x": rig.fov_x,
        "w": rig.width, "h": rig.height,
        "fl_x": rig.focal, "fl_y": rig.focal,
        "cx": 0.5 * rig.width, "cy": 0.5 * rig.height,
        "frames": [{"file_path": f"./{split}/r_{k}", "transform_matrix": p.tolist()} for k, p in enumerate(poses)],
    }
