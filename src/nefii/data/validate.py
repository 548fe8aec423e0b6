"""Checks on what readers found; each failure is one :class:`InputError` naming the file and the problem.

Readers call these on every pose, intrinsics matrix, image and mask, so that bad input stops
at load time with a line such as ``scene/transforms_train.json: frame 3 (./train/r_3): singular
camera pose (det R = 0)`` instead of surfacing as NaNs in training.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError

ORTHONORMAL_TOL = 1e-3
"""largest ``|R^T R - I|`` accepted for a camera rotation (datasets print matrices to ~7 digits)"""


def check_c2w(m: np.ndarray, path: str | Path, where: str) -> np.ndarray:
    """A camera-to-world matrix (3x4 or 4x4) -> 4x4 float64 with a proper rotation block."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]], 0)
    if m.shape != (4, 4):
        raise InputError(path, f"{where}: camera pose has shape {m.shape}, expected 4x4 or 3x4")
    if not np.isfinite(m).all():
        raise InputError(path, f"{where}: camera pose has NaN or infinite entries")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(path, f"{where}: camera pose's last row is {m[3].tolist()}, not [0, 0, 0, 1]")
    R = m[:3, :3]
    det = float(np.linalg.det(R))
    if abs(det) < 1e-8:
        raise InputError(path, f"{where}: singular camera pose (det R = {det:.3g})")
    if det < 0:
        raise InputError(path, f"{where}: camera rotation is a reflection (det R = {det:.3g})")
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ORTHONORMAL_TOL:
        raise InputError(path, f"{where}: camera rotation is not orthonormal (max |R^T R - I| = {err:.3g})")
    return m


def check_K(K: np.ndarray, path: str | Path, where: str) -> np.ndarray:
    """A 3x3 intrinsics matrix -> float64, with positive finite focal lengths and last row 0 0 1."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise InputError(path, f"{where}: intrinsics have shape {K.shape}, expected 3x3")
    if not np.isfinite(K).all():
        raise InputError(path, f"{where}: intrinsics have NaN or infinite entries")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or abs(K[1, 0]) > 1e-9 * max(1.0, abs(K[1, 1])):
        raise InputError(path, f"{where}: intrinsics are not upper triangular with last row [0, 0, 1]")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"{where}: focal lengths must be positive, got fx={K[0, 0]:.6g}, fy={K[1, 1]:.6g}")
    return K


def check_size(shape: tuple[int, ...], path: str | Path, want: tuple[int, int], want_from: str | Path) -> None:
    """``shape[:2]`` must be ``want`` = (H, W), which came from ``want_from``."""
    if tuple(shape[:2]) != tuple(want):
        raise InputError(path, f"size {shape[1]}x{shape[0]} differs from {want[1]}x{want[0]} of {want_from}; "
                               "all views must have the same size")


def check_mask(mask: np.ndarray, path: str | Path) -> None:
    """A mask must cover at least one pixel."""
    if not mask.any():
        raise InputError(path, "mask is empty (no foreground pixel)")
