"""``nefii demo``: for now, render a textured sphere under an SG environment with the MIS estimator.

This exercises the rendering core end to end (SG light, BRDF, three samplers, MIS) and
writes PNGs to look at. It becomes the real fit-and-evaluate demo once ``nefii fit`` exists.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

from ..camera import intrinsics_from_fov, look_at, pixel_rays
from ..io.images import write_png
from ..render.brdf import Material
from ..render.estimator import estimate_Lo
from ..render.frame import dot
from ..render.sg import SGMixture, sg_eval, sg_to_equirect


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the built-in demo (currently: render an SG-lit sphere)",
                       description=__doc__)
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    p.add_argument("--res", type=int, default=128, help="image side in pixels")
    p.add_argument("--spp", type=int, default=64, help="estimator samples per pixel (3 directions each)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def demo_environment(dtype: torch.dtype = torch.float32) -> SGMixture:
    """A small sky: a sharp warm sun, a wide blue sky lobe and a dim brown ground bounce."""
    axis = torch.tensor([[0.5, -0.4, 0.77], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-0.7, 0.7, 0.1]], dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    sharpness = torch.tensor([400.0, 1.5, 2.0, 8.0], dtype=dtype)
    amplitude = torch.tensor([[60.0, 55.0, 45.0], [0.5, 0.7, 1.1], [0.25, 0.18, 0.12], [1.2, 0.5, 0.3]],
                             dtype=dtype)
    return SGMixture(axis, sharpness, amplitude)


def sphere_material(x: torch.Tensor) -> Material:
    """Checkered albedo in latitude/longitude; roughness from 0.1 (left) to 0.9 (right)."""
    theta = torch.acos(x[..., 2].clamp(-1, 1))
    phi = torch.atan2(x[..., 1], x[..., 0])
    check = ((torch.floor(theta / (math.pi / 6)) + torch.floor(phi / (math.pi / 6))) % 2).unsqueeze(-1)
    albedo = torch.where(check > 0, torch.tensor([0.8, 0.25, 0.2]), torch.tensor([0.85, 0.85, 0.8]))
    roughness = (0.1 + 0.8 * (x[..., 0] * 0.5 + 0.5)).clamp(0.089, 1.0)
    return Material(albedo=albedo, roughness=roughness)


def run(args: argparse.Namespace) -> int:
    print("nefii demo: the fit is not built yet; rendering an SG-lit sphere with the MIS estimator instead.")
    t0 = time.time()
    env = demo_environment()
    eye = torch.tensor([0.0, -3.2, 0.8], dtype=torch.float64)
    c2w = look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    o, d = pixel_rays(c2w, intrinsics_from_fov(math.radians(45), args.res, args.res), args.res, args.res)
    o, d = o.reshape(-1, 3).float(), d.reshape(-1, 3).float()

    # ---- unit sphere at the origin: |o + t d|^2 = 1
    b = dot(o, d)
    disc = b * b - (dot(o, o) - 1.0)
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    x = o + t.unsqueeze(-1) * d
    image = sg_eval(d, env)  # background: the environment seen directly

    g = torch.Generator().manual_seed(args.seed)
    idx = hit.nonzero().squeeze(-1)
    for chunk in tqdm(idx.split(2048), desc="rendering", unit="chunk"):
        xc = x[chunk]
        est = estimate_Lo(xc, -d[chunk], sphere_material(xc), env, lambda w: sg_eval(w, env), args.spp, g)
        image[chunk] = est.rgb

    img = image.reshape(args.res, args.res, 3).numpy()
    out = args.out
    write_png(out / "sphere.png", img / (1.0 + img))  # Reinhard tone map, then sRGB
    envimg = sg_to_equirect(env, 128, 256).numpy()
    write_png(out / "envmap.png", envimg / (1.0 + envimg))
    print(f"wrote {out / 'sphere.png'} and {out / 'envmap.png'} in {time.time() - t0:.1f} s")
    return 0
