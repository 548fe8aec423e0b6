"""Tiny scenes in every dataset format nefii reads, all written from the same cameras and images.

``make_truth`` draws a few OpenCV cameras looking at the origin and images whose 8-bit sRGB
codes are exact (so PNG and float32 EXR round trips are lossless); each ``write_*`` writes
them in one format, with the truth's world as the dataset's own world. Every loader must give
back ``Truth.K``, ``Truth.images``, ``Truth.masks`` and, through ``SceneData.source_c2w()``
(which undoes a format's normalisation: NeuS ``scale_mat``, Synthetic4Relight's halving),
``Truth.c2w``.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from nefii.camera import look_at
from nefii.io.exr import write_exr
from nefii.io.images import srgb_to_linear

W, H = 8, 6
GL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV <-> OpenGL camera axes (its own inverse)"""


@dataclass
class Truth:
    K: np.ndarray
    """(3, 3) intrinsics"""
    c2w: np.ndarray
    """(N, 4, 4) OpenCV camera-to-world"""
    srgb8: np.ndarray
    """(N, H, W, 3) uint8 sRGB codes, 0 where alpha is 0"""
    alpha8: np.ndarray
    """(N, H, W) uint8 alpha: 0, 128 or 255"""

    @property
    def n(self) -> int:
        return len(self.c2w)

    @property
    def images(self) -> np.ndarray:
        return srgb_to_linear(self.srgb8 / 255.0)

    @property
    def alpha(self) -> np.ndarray:
        return (self.alpha8 / 255.0).astype(np.float32)

    @property
    def masks(self) -> np.ndarray:
        return self.alpha8 > 127

    @property
    def w2c(self) -> np.ndarray:
        return np.linalg.inv(self.c2w)


def make_truth(n: int = 4, *, seed: int = 0, centred: bool = False) -> Truth:
    """``n`` cameras 2.5-4 units from the origin, looking at it, world +Z up.

    ``centred``: ``fx = fy`` and the principal point at the image centre (what formats that
    only store ``camera_angle_x`` can express); otherwise ``fx != fy`` and an off-centre point.
    """
    rng = np.random.default_rng(seed)
    c2w = []
    for _ in range(n):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.2
        eye = d / np.linalg.norm(d) * rng.uniform(2.5, 4.0)
        c2w.append(look_at(torch.tensor(eye), torch.zeros(3, dtype=torch.float64),
                           torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).numpy())
    K = np.array([[9.5, 0, W / 2], [0, 9.5, H / 2], [0, 0, 1.0]]) if centred else \
        np.array([[9.5, 0, 4.3], [0, 10.25, 2.8], [0, 0, 1.0]])
    alpha8 = np.zeros((n, H, W), np.uint8)
    alpha8[:, 1:5, 2:7] = 255
    alpha8[:, 1:5, 1] = 128  # a soft edge, to test un-premultiplying
    srgb8 = rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)
    srgb8[alpha8 == 0] = 0
    return Truth(K=K, c2w=np.stack(c2w), srgb8=srgb8, alpha8=alpha8)


# ---------------------------------------------------------------------------- small writers

def save_png(path: Path, u8: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(u8).save(path)


def save_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1))


def rgba8(t: Truth, i: int) -> np.ndarray:
    return np.concatenate([t.srgb8[i], t.alpha8[i][..., None]], -1)


def premultiplied(t: Truth, i: int) -> np.ndarray:
    return np.concatenate([t.images[i] * t.alpha[i][..., None], t.alpha[i][..., None]], -1)


def mask8(t: Truth, i: int) -> np.ndarray:
    return np.where(t.masks[i], 255, 0).astype(np.uint8)


def fov_x(t: Truth) -> float:
    return 2.0 * math.atan(0.5 * W / t.K[0, 0])


# ---------------------------------------------------------------------------- the formats

def write_nefii(root: Path, t: Truth, split: str = "train", *, indices=None, exr: bool = True, png: bool = True,
                half: bool = False, suffix_in_path: str = "", extras: bool = True) -> None:
    """nefii layout: transforms json with fl_x.., RGBA EXR (premultiplied) and RGBA PNG; on the test
    split also ground-truth maps, ``_mask.png`` and two relit environments; ``mesh.ply``, ``envmap.exr``."""
    indices = list(range(t.n)) if indices is None else list(indices)
    frames = []
    for i, k in enumerate(indices):
        stem = root / split / f"r_{k}"
        if exr:
            write_exr(stem.with_suffix(".exr"), premultiplied(t, i), half=half)
        if png:
            save_png(stem.with_suffix(".png"), rgba8(t, i))
        frames.append({"file_path": f"./{split}/r_{k}{suffix_in_path}", "transform_matrix": (t.c2w[i] @ GL).tolist()})
        if split == "test" and extras:
            rng = np.random.default_rng(k)
            for kind, c in (("albedo", 3), ("roughness", 1), ("specular", 3), ("diffuse", 3), ("normal", 3),
                            ("depth", 1)):
                write_exr(root / split / f"r_{k}_{kind}.exr", rng.uniform(size=(H, W, c) if c == 3 else (H, W)))
            save_png(root / split / f"r_{k}_mask.png", mask8(t, i))
            for env in ("sunset", "studio"):
                write_exr(root / "relight" / env / f"r_{k}.exr", premultiplied(t, i) * [0.5, 0.5, 0.5, 1.0])
    save_json(root / f"transforms_{split}.json", {
        "camera_angle_x": fov_x(t), "w": W, "h": H,
        "fl_x": t.K[0, 0], "fl_y": t.K[1, 1], "cx": t.K[0, 2], "cy": t.K[1, 2], "frames": frames})
    if extras:
        write_exr(root / "envmap.exr", np.full((4, 8, 3), 0.25, np.float32))
        (root / "mesh.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                       "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                       "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
        if split == "test":
            for env in ("sunset", "studio"):
                write_exr(root / "relight" / f"{env}.exr", np.ones((4, 8, 3), np.float32))


def write_nerf_synthetic(root: Path, t: Truth, split: str = "train") -> None:
    """Plain NeRF-synthetic: ``camera_angle_x`` only, RGBA PNGs, ``file_path`` without suffix."""
    frames = []
    for i in range(t.n):
        save_png(root / split / f"r_{i}.png", rgba8(t, i))
        frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": (t.c2w[i] @ GL).tolist()})
    save_json(root / f"transforms_{split}.json", {"camera_angle_x": fov_x(t), "frames": frames})


def write_synthetic4relight(root: Path, t: Truth, split: str = "train") -> None:
    """Synthetic4Relight: OpenCV camera-to-world (the reader halves translations)."""
    frames = []
    for i in range(t.n):
        frames.append({"file_path": f"{split}/{i}", "transform_matrix": t.c2w[i].tolist()})
        if split == "train":
            write_exr(root / split / f"{i}_rgb.exr", t.images[i])
            save_png(root / split / f"{i}_mask.png", mask8(t, i))
        else:
            save_png(root / split / f"{i}_rgba.png", rgba8(t, i))
            save_png(root / split / f"{i}_albedo.png", t.srgb8[i])
            save_png(root / split / f"{i}_rough.png", t.srgb8[i][..., 0])
    save_json(root / f"transforms_{split}.json", {"camera_angle_x": fov_x(t), "frames": frames})


NEUS_SCALE_MAT = np.array([[1.7, 0, 0, 0.2], [0, 1.7, 0, -0.1], [0, 0, 1.7, 0.3], [0, 0, 0, 1.0]])
"""normalised -> dataset world, as NeuS's ``scale_mat``"""


def write_neus(root: Path, t: Truth, scale_mat: np.ndarray | None = NEUS_SCALE_MAT, *,
               name: str = "cameras_sphere.npz") -> None:
    """NeuS: ``world_mat = K [R | t]`` in the truth's world; ``scale_mat`` (omitted if ``None``)."""
    arrays = {}
    for i in range(t.n):
        K4 = np.eye(4)
        K4[:3, :3] = t.K
        arrays[f"world_mat_{i}"] = K4 @ t.w2c[i]
        if scale_mat is not None:
            arrays[f"scale_mat_{i}"] = scale_mat
        save_png(root / "image" / f"{i:03d}.png", t.srgb8[i])
        save_png(root / "mask" / f"{i:03d}.png", mask8(t, i))
    np.savez(root / name, **arrays)


def write_physg(root: Path, t: Truth) -> None:
    """PhySG: per image K (4x4) and W2C (4x4), flattened, OpenCV."""
    cams = {}
    for i in range(t.n):
        K4 = np.eye(4)
        K4[:3, :3] = t.K
        name = f"{i:03d}.png"
        cams[name] = {"K": K4.flatten().tolist(), "W2C": t.w2c[i].flatten().tolist(), "img_size": [W, H]}
        save_png(root / "image" / name, t.srgb8[i])
        save_png(root / "mask" / name, mask8(t, i))
    save_json(root / "cam_dict_norm.json", cams)


def write_colmap(root: Path, t: Truth, *, binary: bool, masks: bool = True, model: str = "PINHOLE",
                 extra: tuple[float, ...] = ()) -> None:
    """COLMAP sparse model written by pycolmap; images in ``images/``, masks ``masks/<name>.png``.

    ``extra``: the model's parameters after the focal length(s) and principal point; models with
    one focal length (``SIMPLE_*``, ``RADIAL``, ``RADIAL_FISHEYE``) get ``fx``."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    fx, fy, cx, cy = t.K[0, 0], t.K[1, 1], t.K[0, 2], t.K[1, 2]
    one_focal = model.startswith("SIMPLE_") or model in ("RADIAL", "RADIAL_FISHEYE")
    params = [fx, cx, cy] if one_focal else [fx, fy, cx, cy]
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params + list(extra),
                                                    camera_id=1))
    for i in range(t.n):
        name = f"r_{i}.png"
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i + 1),
                                         pycolmap.Rigid3d(t.w2c[i][:3, :4]))
        save_png(root / "images" / name, t.srgb8[i])
        if masks:
            save_png(root / "masks" / f"{name}.png", mask8(t, i))
    out = root / "sparse" / "0"
    out.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(out))
