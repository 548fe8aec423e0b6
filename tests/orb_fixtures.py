"""Tiny scenes in Stanford-ORB's blender layout, written as the benchmark ships them (docs/datasets.md):

    <data>/blender_HDR/<scene>/transforms_{train,test,novel}.json, {train,test}/NNNN.exr, {train,test}_mask/NNNN.png
    <data>/blender_HDR/<other>/test/NNNN.exr, test_mask/NNNN.png       the novel-light photographs
    <data>/ground_truth/<scene|other>/env_map/NNNN.exr                  each test photograph's map, camera frame
    <data>/ground_truth/<scene>/mesh_blender/mesh.obj

Environment maps are written from a world-frame light ``f(d)`` through Stanford-ORB's own convention, in
Blender camera axes as its ``orb/utils/env_map.py`` states it (texel ``(i, j)`` of ``h x w`` at
``u = j / (w - 1)``, ``v = i / (h - 1)``; direction ``(sin t sin a, cos t, -sin t cos a)`` with
``a = 2 pi u - pi``, ``t = pi v``), independently of the reader, which goes the other way.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from data_fixtures import GL, Truth, fov_x, mask8, save_json, save_png
from nefii.io.exr import write_exr

SCENE = "toy_scene001"
OTHERS = ("toy_scene002", "toy_scene003")
ENV_H, ENV_W = 24, 48

Light = Callable[[np.ndarray], np.ndarray]
"""world direction(s) ``(..., 3)`` -> radiance ``(..., 3)``"""


def lobe_light(axis=(0.3, -0.5, 0.8), colour=(3.0, 2.0, 1.0), base=0.2) -> Light:
    """A smooth light: ``base + colour * max(0, d . axis)^2``."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)

    def f(d: np.ndarray) -> np.ndarray:
        return base + np.asarray(colour) * np.maximum(0.0, d @ a)[..., None] ** 2
    return f


def orb_texel_directions_gl(h: int, w: int) -> np.ndarray:
    """``(h, w, 3)`` unit directions of Stanford-ORB's texels in Blender camera axes (x right, y up, z back)."""
    u = np.arange(w) / (w - 1)
    v = np.arange(h) / (h - 1)
    a = 2.0 * math.pi * u[None, :] - math.pi
    t = math.pi * v[:, None]
    return np.stack([np.sin(t) * np.sin(a), np.cos(t) * np.ones_like(a), -np.sin(t) * np.cos(a)], -1)


def camera_frame_envmap(light: Light, c2w_cv: np.ndarray, h: int = ENV_H, w: int = ENV_W) -> np.ndarray:
    """The map Stanford-ORB stores for a photograph taken by ``c2w_cv`` under the world light ``light``."""
    R_gl = (c2w_cv @ GL)[:3, :3]                     # the transform_matrix's rotation
    return light(orb_texel_directions_gl(h, w) @ R_gl.T).astype(np.float32)


def _frame(t: Truth, i: int, file_path: str, **extra) -> dict:
    return {"file_path": file_path, "transform_matrix": (t.c2w[i] @ GL).tolist(), **extra}


def write_views(folder: Path, split: str, t: Truth, numbers: list[int], *, hdr: bool = True) -> list[str]:
    """``<split>/NNNN.exr|png`` and ``<split>_mask/NNNN.png``; the file_paths (``./<split>/NNNN``)."""
    paths = []
    for i, k in enumerate(numbers):
        stem = f"{k:04d}"
        if hdr:
            write_exr(folder / split / f"{stem}.exr", t.images[i])
        else:
            save_png(folder / split / f"{stem}.png", t.srgb8[i])
        save_png(folder / f"{split}_mask" / f"{stem}.png", mask8(t, i))
        paths.append(f"./{split}/{stem}")
    return paths


def write_orb(data: Path, train: Truth, test: Truth, novel: dict[str, Truth], lights: dict[str, Light], *,
              hdr: bool = True, mesh: str | None = None, novel_angle_top_level: bool = False) -> Path:
    """One scene ``SCENE`` under ``data/blender_HDR`` (``blender_LDR`` with ``hdr=False``) and the novel-light
    photographs of ``novel`` (capture scene -> its views, lit by ``lights[scene]``); returns the scene folder.
    Test views are numbered from 10, each capture's from 20, 30, ..."""
    variant = data / ("blender_HDR" if hdr else "blender_LDR")
    root = variant / SCENE
    angle = fov_x(train)
    frames = [_frame(train, i, p) for i, p in enumerate(write_views(root, "train", train, list(range(train.n)),
                                                                     hdr=hdr))]
    save_json(root / "transforms_train.json", {"camera_angle_x": angle, "frames": frames})
    numbers = [10 + i for i in range(test.n)]
    frames = [_frame(test, i, p) for i, p in enumerate(write_views(root, "test", test, numbers, hdr=hdr))]
    save_json(root / "transforms_test.json", {"camera_angle_x": angle, "frames": frames})
    for i, k in enumerate(numbers):
        write_exr(data / "ground_truth" / SCENE / "env_map" / f"{k:04d}.exr",
                  camera_frame_envmap(lights[SCENE], test.c2w[i]))
    novel_frames = []
    for s, (name, t) in enumerate(novel.items()):
        numbers = [20 + 10 * s + i for i in range(t.n)]
        paths = write_views(variant / name, "test", t, numbers, hdr=hdr)
        for i, (k, p) in enumerate(zip(numbers, paths)):
            extra = {} if novel_angle_top_level else {"camera_angle_x": fov_x(t)}
            novel_frames.append(_frame(t, i, p, scene_name=name, **extra))
            write_exr(data / "ground_truth" / name / "env_map" / f"{k:04d}.exr",
                      camera_frame_envmap(lights[name], t.c2w[i]))
    top = {"camera_angle_x": angle} if novel_angle_top_level else {}
    save_json(root / "transforms_novel.json", {**top, "frames": novel_frames})
    if mesh is not None:
        path = data / "ground_truth" / SCENE / "mesh_blender" / "mesh.obj"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(mesh)
    return root


TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def write_rendered_orb(data: Path, res: int = 16, n_train: int = 6, n_test: int = 2, n_novel: int = 2,
                       seed: int = 0) -> Path:
    """``fit_fixtures``' ball on a slab rendered by nefii's estimator in Stanford-ORB's layout: train and test
    under ``scene_env``, each capture of ``OTHERS`` at its own poses under one of ``relight_envs``, with
    its maps stored in each camera's frame. The scan is ``scene_mesh``; returns the scene folder."""
    from fit_fixtures import relight_envs, render, scene_env, scene_mesh
    from nefii.camera import intrinsics_from_fov, look_at
    from nefii.raycast import MeshGeometry
    from nefii.render.sg import sg_eval

    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    gen = torch.Generator().manual_seed(seed)
    fov = math.radians(40.0)
    K = intrinsics_from_fov(fov, res, res)
    envs = {SCENE: scene_env(), **dict(zip(OTHERS, relight_envs().values()))}

    def light(env) -> Light:
        return lambda d: sg_eval(torch.from_numpy(d).float(), env).double().numpy()

    def cameras(n: int, phase: float, height: float) -> list[torch.Tensor]:
        return [look_at(torch.tensor([2.6 * math.cos(a), 2.6 * math.sin(a), height], dtype=torch.float64),
                        torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
                for a in (2 * math.pi * (k + phase) / n for k in range(n))]

    def shoot(folder: Path, split: str, name: str, c2ws: list[torch.Tensor], first: int) -> list[dict]:
        frames = []
        for i, c2w in enumerate(c2ws):
            rgb, mask, *_ = render(geometry, envs[name], c2w, K, res, gen)
            stem = f"{first + i:04d}"
            write_exr(folder / split / f"{stem}.exr", rgb)
            save_png(folder / f"{split}_mask" / f"{stem}.png", np.where(mask, 255, 0).astype(np.uint8))
            if split == "test":
                write_exr(data / "ground_truth" / name / "env_map" / f"{stem}.exr",
                          camera_frame_envmap(light(envs[name]), c2w.numpy(), 64, 128))
            frames.append({"file_path": f"./{split}/{stem}", "transform_matrix": (c2w.numpy() @ GL).tolist()})
        return frames

    root = data / "blender_HDR" / SCENE
    for split, n, phase, first in (("train", n_train, 0.0, 0), ("test", n_test, 0.5, 10)):
        frames = shoot(root, split, SCENE, cameras(n, phase, 1.3), first)
        save_json(root / f"transforms_{split}.json", {"camera_angle_x": fov, "frames": frames})
    novel = []
    for s, name in enumerate(OTHERS):
        frames = shoot(data / "blender_HDR" / name, "test", name, cameras(n_novel, 0.25 + 0.3 * s, 1.0 + 0.4 * s),
                       20 + 10 * s)
        novel += [{**f, "scene_name": name, "camera_angle_x": fov} for f in frames]
    save_json(root / "transforms_novel.json", {"frames": novel})
    obj = data / "ground_truth" / SCENE / "mesh_blender" / "mesh.obj"
    obj.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(obj)
    return root
