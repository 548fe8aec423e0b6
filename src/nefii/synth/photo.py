"""A ground-truth scene as a phone would photograph it (``nefii synth SCENE --photo``).

From a clean scene in the nefii layout (linear RGBA EXR renders, ``envmap.exr``), each view becomes a
capture as nerfstudio's ``ns-process-data`` would hand it over:

1. the environment composited behind the object (a photo has a background, and no mask);
2. Brown-Conrady lens distortion (``k1``, ``k2``): OpenCV's ``undistortPoints`` says where each photo pixel
   looks in the pinhole render, which is resampled there; the photo's focal length is the render's times
   the zoom that keeps every photo pixel inside the render;
3. a per-view exposure (``2^u``, ``u`` uniform in +-``ev`` stops, recorded as the EXIF exposure time as a
   phone records it) and white-balance drift (a log-normal gain per channel, not recorded), on top of one
   exposure for the scene that puts the object's brightest 0.5% of pixels over 1 (metered on the subject; the sky behind it clips more);
4. sensor noise: shot noise (variance proportional to the signal) and read noise, in linear light;
5. highlights clipped at 1, the sRGB curve, 8 bits, JPEG at ``quality``.

Written: ``images/frame_NNNNN.jpg``, ``transforms.json`` (``OPENCV`` with the distortion, OpenGL poses,
``train_filenames`` and ``test_filenames``) and ``photo.json`` (what was done to each view, for scoring:
its true gain, and where the clean scene is). The clean scene's test split holds the ground truth; score
a fit of the photos with ``nefii eval RUN --data CLEAN``.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..camera import pixel_rays
from ..data import load_scene
from ..data.undistort import PIXEL_CENTRE
from ..errors import InputError
from ..io.atomic import atomic_dir
from ..io.exr import read_exr
from ..io.images import linear_to_srgb, to_uint8
from ..render.envmap import envmap_lookup

GL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV <-> OpenGL camera axes"""


@dataclass(frozen=True)
class PhotoSettings:
    """How the phone takes the pictures."""

    k1: float = -0.1
    """radial distortion (negative: barrel, as a phone's wide lens)"""
    k2: float = 0.01
    """second radial coefficient"""
    ev: float = 1.0
    """per-view exposure drawn uniformly within +-ev stops"""
    white_balance: float = 0.05
    """standard deviation of the per-channel log gain (white-balance drift)"""
    clip_share: float = 0.005
    """share of the object's pixels over 1 at the mean exposure (the highlights a phone clips)"""
    shot_noise: float = 2.5e-3
    """shot-noise variance per unit of linear signal (a full-scale pixel collects ~400 electrons)"""
    read_noise: float = 2e-3
    """standard deviation of the read noise, linear"""
    quality: int = 90
    """JPEG quality"""
    seed: int = 0
    """seeds exposures, white balance and noise"""


def photo_K(K: np.ndarray, D: np.ndarray, width: int, height: int) -> np.ndarray:
    """The photo's pinhole part: ``K`` with its focal lengths scaled up so that every pixel of the distorted
    photo looks inside the ``K`` render (nefii pixel convention)."""
    import cv2

    K_cv = np.linalg.inv(PIXEL_CENTRE) @ K
    t = np.linspace(0.0, 1.0, 65)
    edge = np.concatenate([np.stack([t * width, np.full_like(t, y)], -1) for y in (0, height)]
                          + [np.stack([np.full_like(t, x), t * height], -1) for x in (0, width)]) - 0.5
    half = np.array([K_cv[0, 2] + 0.5, width - 0.5 - K_cv[0, 2], K_cv[1, 2] + 0.5, height - 0.5 - K_cv[1, 2]])
    zoom = 1.0
    for _ in range(50):  # grow the zoom until the photo's border (pixel edges) looks inside the render's
        Kp = K_cv.copy()
        Kp[:2, :2] *= zoom
        xy = cv2.undistortPoints(edge[:, None, :], Kp, D).reshape(-1, 2) * np.array([K_cv[0, 0], K_cv[1, 1]])
        reach = max(-xy[:, 0].min() / half[0], xy[:, 0].max() / half[1], -xy[:, 1].min() / half[2],
                    xy[:, 1].max() / half[3])
        if reach <= 1.0:
            break
        zoom *= reach * 1.001
    out = K.copy()
    out[0, 0] *= zoom
    out[1, 1] *= zoom
    return out


def distortion_maps(K_render: np.ndarray, K_photo: np.ndarray, D: np.ndarray, width: int,
                    height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per photo pixel, where it looks in the pinhole render (OpenCV float maps x, y)."""
    import cv2

    j, i = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([j, i], -1).reshape(-1, 1, 2)  # OpenCV pixel centres
    K_photo_cv = np.linalg.inv(PIXEL_CENTRE) @ K_photo
    xy = cv2.undistortPoints(pts, K_photo_cv, D).reshape(-1, 2)
    K_cv = np.linalg.inv(PIXEL_CENTRE) @ K_render
    mx = (K_cv[0, 0] * xy[:, 0] + K_cv[0, 2]).reshape(height, width).astype(np.float32)
    my = (K_cv[1, 1] * xy[:, 1] + K_cv[1, 2]).reshape(height, width).astype(np.float32)
    return mx, my


def distort(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """A pinhole render resampled into the distorted photo (bilinear, borders replicated)."""
    import cv2

    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _composited(clean: Path, name: str, envmap: torch.Tensor, c2w: torch.Tensor, K: torch.Tensor,
                height: int, width: int) -> np.ndarray:
    """The clean render with the environment behind it: ``rgb + (1 - alpha) E(d)`` (linear)."""
    rgba = read_exr(clean / name)
    if rgba.ndim != 3 or rgba.shape[-1] != 4:
        raise InputError(clean / name, "expected a premultiplied RGBA render (nefii layout)")
    _, d = pixel_rays(c2w, K, height, width)
    background = envmap_lookup(envmap, d.float()).numpy()
    return rgba[..., :3] + (1.0 - rgba[..., 3:]) * background


SHUTTER = 1.0 / 120.0
"""the exposure time of a view at 0 stops (s); ISO 100 and f/1.8 throughout, as a phone's fixed aperture"""


def _exif(stops: float):
    """The EXIF a phone writes for a view ``stops`` brighter than the scene's exposure: its shutter time
    (white balance, which a phone does not record as a gain, stays for the fit to find)."""
    from PIL import ExifTags, Image

    exif = Image.Exif()
    exif[ExifTags.IFD.Exif] = {ExifTags.Base.ExposureTime: SHUTTER * 2.0**stops, ExifTags.Base.FNumber: 1.8,
                               ExifTags.Base.ISOSpeedRatings: 100}
    return exif


def _check_same_views(render: dict, clean: dict, where: Path) -> None:
    """``render``'s splits are ``clean``'s views at an integer multiple of its resolution."""
    for split, r in render.items():
        c = clean[split]
        m = r.width // c.width
        ok = (len(r) == len(c) and m >= 1 and (r.width, r.height) == (m * c.width, m * c.height)
              and torch.allclose(r.cameras.c2w, c.cameras.c2w, atol=1e-6)
              and torch.allclose(r.cameras.K[:, :2], m * c.cameras.K[:, :2], rtol=1e-6))
        if not ok:
            raise InputError(where, f"its {split} views are not the clean scene's at an integer multiple of its "
                                    "resolution (render it with the same scene, views and seed)")


def make_photos(clean: str | Path, out: str | Path, settings: PhotoSettings = PhotoSettings(),
                render: str | Path | None = None) -> Path:
    """Photograph the clean nefii-layout scene ``clean`` into ``out`` (written whole or not at all).

    ``render``: the same views rendered at an integer multiple of ``clean``'s resolution (same seed); the
    photos are then taken from it at its resolution, as a camera with more pixels than the fit uses would
    take them (a fit averages them down, ``max_image_side``), instead of resampled from ``clean``'s own
    pixels: resampling a render at its own resolution blurs it twice over (distortion here, undistortion
    when it is read) in a way a camera's pixels do not."""
    from PIL import Image

    clean, out = Path(clean).resolve(), Path(out)
    source = clean if render is None else Path(render).resolve()
    splits = {s: load_scene(source, s, format="nerf") for s in ("train", "test")}
    if render is not None:
        _check_same_views(splits, {s: load_scene(clean, s, format="nerf") for s in ("train", "test")}, source)
    envmap = splits["train"].envmap
    if envmap is None:
        raise InputError(clean / "envmap.exr", "not found: the photo's background needs the scene's environment")
    h, w = splits["train"].height, splits["train"].width
    D = np.array([settings.k1, settings.k2, 0.0, 0.0])
    rng = np.random.default_rng(settings.seed)
    views = [(s, i) for s in ("train", "test") for i in range(len(splits[s]))]
    linear = {}
    for s, i in views:
        sc = splits[s]
        linear[s, i] = _composited(source, sc.names[i], envmap, sc.cameras.c2w[i], sc.cameras.K[i], h, w)
    lum = np.concatenate([(linear[v] @ np.array([0.2126, 0.7152, 0.0722]))[splits[v[0]].masks[v[1]].numpy()]
                          for v in views])  # metered on the object, as a phone's auto exposure on its subject
    base = 1.0 / max(float(np.quantile(lum, 1.0 - settings.clip_share)), 1e-6)
    frames, record = [], []
    with atomic_dir(out) as tmp:
        (tmp / "images").mkdir()
        for n, (s, i) in enumerate(views):
            sc = splits[s]
            K = sc.cameras.K[i].numpy()
            K_photo = photo_K(K, D, w, h)
            img = distort(linear[s, i].astype(np.float32), distortion_maps(K, K_photo, D, w, h))
            stops = float(rng.uniform(-settings.ev, settings.ev))
            gain = base * 2.0**stops * np.exp(rng.normal(0.0, settings.white_balance, 3))
            img = np.clip(img * gain, 0.0, None)
            img = img + np.sqrt(settings.shot_noise * img + settings.read_noise**2) * rng.standard_normal(img.shape)
            name = f"images/frame_{n + 1:05d}.jpg"
            Image.fromarray(to_uint8(linear_to_srgb(img))).save(tmp / name, quality=settings.quality,
                                                                 exif=_exif(stops))
            frames.append({"file_path": name, "transform_matrix": (sc.cameras.c2w[i].numpy() @ GL).tolist(),
                           "fl_x": float(K_photo[0, 0]), "fl_y": float(K_photo[1, 1]),
                           "cx": float(K_photo[0, 2]), "cy": float(K_photo[1, 2])})
            record.append({"file_path": name, "clean": sc.names[i], "split": s,
                           "gain": [float(g) for g in gain], "stops": stops})
        meta = {"camera_model": "OPENCV", "w": w, "h": h, "k1": settings.k1, "k2": settings.k2, "p1": 0.0,
                "p2": 0.0, "frames": frames,
                "train_filenames": [f["file_path"] for f, r in zip(frames, record) if r["split"] == "train"],
                "test_filenames": [f["file_path"] for f, r in zip(frames, record) if r["split"] == "test"]}
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=1) + "\n")
        (tmp / "photo.json").write_text(json.dumps({"clean": str(clean), "settings": asdict(settings),
                                                    "base_exposure": base, "views": record}, indent=1) + "\n")
    return out
