"""A tiny scene rendered by nefii's own estimator (direct light with visibility), in the nefii
layout: enough for end-to-end runs of fit and eval in seconds. Not a ground-truth benchmark
(that is ``nefii synth``, rendered by Mitsuba): it only has to be consistent."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch
import trimesh

from nefii.camera import intrinsics_from_fov, look_at, pixel_rays
from nefii.raycast import MeshGeometry, Rays, spawn_rays
from nefii.io.exr import write_exr
from nefii.io.images import write_png
from nefii.render.brdf import BRDFModel, Material
from nefii.render.estimator import estimate_Lo
from nefii.render.sg import SGMixture, sg_eval, sg_to_equirect

GL = np.diag([1.0, -1.0, -1.0, 1.0])


def scene_mesh() -> trimesh.Trimesh:
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.45).apply_translation((0.0, 0.0, 0.05))
    slab = trimesh.creation.box((1.6, 1.6, 0.1)).apply_translation((0.0, 0.0, -0.45))
    return trimesh.util.concatenate([ball, slab])


def scene_env() -> SGMixture:
    axis = torch.tensor([[0.4, -0.3, 0.87], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return SGMixture(axis, torch.tensor([80.0, 1.0, 2.0]),
                     torch.tensor([[20.0, 19.0, 17.0], [0.6, 0.7, 0.9], [0.2, 0.15, 0.1]]))


def relight_envs() -> dict[str, SGMixture]:
    """Two other environments for ``relight/<name>/`` (a low warm sun; a cool sun from the other side)."""
    axes = torch.tensor([[-0.6, 0.55, 0.45], [0.0, 0.0, 1.0]])
    axes = axes / axes.norm(dim=-1, keepdim=True)
    dusk = SGMixture(axes, torch.tensor([60.0, 1.5]), torch.tensor([[18.0, 10.0, 4.0], [0.3, 0.3, 0.45]]))
    axes2 = torch.tensor([[0.5, 0.7, 0.5], [0.0, 0.0, 1.0]])
    axes2 = axes2 / axes2.norm(dim=-1, keepdim=True)
    dawn = SGMixture(axes2, torch.tensor([40.0, 1.0]), torch.tensor([[8.0, 10.0, 14.0], [0.5, 0.45, 0.4]]))
    return {"dusk": dusk, "dawn": dawn}


def scene_material(x: torch.Tensor, n: torch.Tensor | None = None) -> Material:
    red = (x[..., 0] > 0).float().unsqueeze(-1)
    albedo = red * torch.tensor([0.7, 0.2, 0.15]) + (1 - red) * torch.tensor([0.3, 0.5, 0.7])
    roughness = torch.where(x[..., 2] > -0.38, 0.3, 0.8).to(x.dtype)
    return Material(albedo, roughness)


def render(geometry: MeshGeometry, env: SGMixture, c2w: torch.Tensor, K: torch.Tensor, res: int,
           gen: torch.Generator, spp: int = 16, brdf: BRDFModel = BRDFModel()):
    o, d = pixel_rays(c2w, K, res, res)
    o, d = o.reshape(-1, 3).float(), d.reshape(-1, 3).float()
    hit = geometry.intersect(Rays(o, d))
    rgb = sg_eval(d, env)
    spec = torch.zeros_like(rgb)
    v = hit.valid
    x, n, ng = hit.position[v], hit.normal[v], hit.geometric_normal[v]

    def incoming(wi):
        rays = spawn_rays(x.unsqueeze(1).expand_as(wi), ng.unsqueeze(1).expand_as(wi), wi, 1e-4 * geometry.scale)
        return sg_eval(wi, env) * (~geometry.occluded(rays)).unsqueeze(-1)

    mat = dataclasses.replace(scene_material(x), brdf=brdf)
    est = estimate_Lo(n, -d[v], mat, env, incoming, spp, gen)
    rgb[v] = est.rgb
    spec[v] = est.specular
    albedo = torch.zeros_like(rgb)
    albedo[v] = mat.albedo
    rough = torch.zeros(len(rgb))
    rough[v] = mat.roughness
    shape = (res, res)
    return (rgb.reshape(*shape, 3).numpy(), v.reshape(shape).numpy(), albedo.reshape(*shape, 3).numpy(),
            rough.reshape(shape).numpy(), spec.reshape(*shape, 3).numpy())


def write_rendered_scene(root: Path, res: int = 16, n_train: int = 6, n_test: int = 2, seed: int = 0,
                         relight: bool = False) -> Path:
    """The scene; with ``relight``, also the test views under :func:`relight_envs` (``relight/<name>/r_K.exr``
    and ``relight/<name>.exr``, as ``nefii synth`` writes them)."""
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    env = scene_env()
    gen = torch.Generator().manual_seed(seed)
    fov = math.radians(40.0)
    K = intrinsics_from_fov(fov, res, res)
    root.mkdir(parents=True, exist_ok=True)
    for split, n, phase in (("train", n_train, 0.0), ("test", n_test, 0.5)):
        frames = []
        for k in range(n):
            a = 2 * math.pi * (k + phase) / n
            eye = torch.tensor([2.6 * math.cos(a), 2.6 * math.sin(a), 1.3], dtype=torch.float64)
            c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
            rgb, mask, albedo, rough, spec = render(geometry, env, c2w, K, res, gen)
            alpha = mask.astype(np.float32)[..., None]
            write_exr(root / split / f"r_{k}.exr", np.concatenate([rgb * alpha, alpha], -1))
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": (c2w.numpy() @ GL).tolist()})
            if split == "test":
                write_exr(root / split / f"r_{k}_albedo.exr", albedo)
                write_exr(root / split / f"r_{k}_roughness.exr", rough)
                write_exr(root / split / f"r_{k}_specular.exr", spec)
                write_png(root / split / f"r_{k}_mask.png", mask.astype(np.float32), srgb=False)
                for name, other in (relight_envs() if relight else {}).items():
                    relit = render(geometry, other, c2w, K, res, gen)[0]
                    write_exr(root / "relight" / name / f"r_{k}.exr", np.concatenate([relit * alpha, alpha], -1))
        f = float(K[0, 0])
        (root / f"transforms_{split}.json").write_text(json.dumps({
            "camera_angle_x": fov, "w": res, "h": res, "fl_x": f, "fl_y": f, "cx": res / 2, "cy": res / 2,
            "frames": frames}))
    mesh.export(root / "mesh.ply")
    write_exr(root / "envmap.exr", sg_to_equirect(env, 32, 64).numpy())
    for name, other in (relight_envs() if relight else {}).items():
        write_exr(root / "relight" / f"{name}.exr", sg_to_equirect(other, 32, 64).numpy())
    return root


def stopped_after_first_call(fn):
    """``fn`` that works once and then raises ``KeyboardInterrupt`` (a Ctrl-C during the second view)."""
    calls = []

    def wrapped(*args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(1)
        return fn(*args, **kwargs)
    return wrapped
