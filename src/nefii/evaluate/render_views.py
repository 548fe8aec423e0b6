"""Render what a fitted model predicts for a camera: path-traced colour and its parts, the
material, the normal and the radiance cache's own colour (its "neural rendering").

Pixels are box-filtered, as the ground truth of a renderer is (``nefii synth``'s colour and material
layers average each pixel's jittered samples). The material layers (albedo, roughness, normal, the cache's
colour) and the mask are the mean over 4 x 4 stratified sub-pixel rays whatever the sample count; the
path-traced colour over ``k x k`` of them, ``k`` the largest with ``k^2 <= min(spp, 16)``, each traced with
``spp // k^2`` estimator samples. Reading the material only at pixel centres would compare a point
sample with a pixel average, which caps even the true material at 24-30 dB albedo PSNR on the
built-in scenes (docs/experiments.md, 2026-11-25); with the material on the colour's grid, an eval at
4 spp scored a fit 0.9 dB below the same fit at 64 spp (docs/experiments.md, 2026-11-30).
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, fields

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from ..camera import jittered_pixel_rays
from ..data.scene import Cameras
from ..fit.model import NeFIIModel, decode_material
from ..fit.path_trace import SurfacePoints, Transport, path_trace
from ..raycast.base import Geometry, Rays, SurfaceHit
from ..render.frame import normalize

MAX_SUBPIXELS = 16
"""sub-pixel rays per pixel at most (4 x 4)"""


@dataclass(frozen=True)
class ViewPrediction:
    """One view; linear values; object quantities are 0 outside ``mask``."""

    rgb: Float[Tensor, "H W 3"] | None
    """path-traced colour (Eq. 2-4) on the object, the environment where the view ray escapes (None: the
    material only was rendered, ``num_samples = 0``)"""
    specular: Float[Tensor, "H W 3"] | None
    """the specular lobe's share of ``rgb`` on the object"""
    diffuse: Float[Tensor, "H W 3"] | None
    albedo: Float[Tensor, "H W 3"]
    roughness: Float[Tensor, "H W"]
    normal: Float[Tensor, "H W 3"]
    cache: Float[Tensor, "H W 3"]
    """the radiance cache's L(x, n, wo) at the first hits"""
    mask: Bool[Tensor, "H W"]
    """where at least half the pixel's sub-pixel rays hit the geometry"""


def subpixel_grid(spp: int) -> int:
    """``k``: the pixel is sampled by ``k x k`` strata."""
    return max(1, math.isqrt(min(max(spp, 1), MAX_SUBPIXELS)))


def subpixel_samples(num_pixels: int, k: int, generator: torch.Generator | None, device: torch.device | str
                     ) -> tuple[Int[Tensor, " R"], Float[Tensor, "R 2"]]:
    """``k x k`` rays per pixel: each ray's flat pixel and its offset in the pixel (``[0, 1)^2``, float64), one
    uniform point in each stratum; the pixel centre when ``k == 1``."""
    pixel = torch.arange(num_pixels, device=device).repeat_interleave(k * k)
    if k == 1:
        return pixel, torch.full((num_pixels, 2), 0.5, dtype=torch.float64, device=device)
    cell = torch.arange(k * k, device=device).repeat(num_pixels)
    jitter = torch.rand(len(pixel), 2, generator=generator, device=device, dtype=torch.float32).double()
    return pixel, (torch.stack([cell % k, cell // k], -1).double() + jitter) / k


@dataclass(frozen=True)
class _Layers:
    """What rays saw, one row per ray (a chunk's) or summed over each pixel's rays (a view's); linear values."""

    rgb: Float[Tensor, "N 3"]
    specular: Float[Tensor, "N 3"]
    diffuse: Float[Tensor, "N 3"]
    albedo: Float[Tensor, "N 3"]
    normal: Float[Tensor, "N 3"]
    cache: Float[Tensor, "N 3"]
    roughness: Float[Tensor, " N"]

    @staticmethod
    def zeros(n: int, device: torch.device) -> "_Layers":
        return _Layers(*(torch.zeros((n, 3) if f.name != "roughness" else (n,), device=device)
                         for f in fields(_Layers)))

    def add_at(self, index: Int[Tensor, " R"], rows: "_Layers") -> None:
        """Sum ``rows`` (one per ray) into the rows ``index`` of these, in place."""
        for f in fields(_Layers):
            getattr(self, f.name).index_add_(0, index, getattr(rows, f.name))

    def divided(self, count: Float[Tensor, " N"]) -> "_Layers":
        """Each row over ``count`` (at least 1): a sum's mean."""
        inv = 1.0 / count.clamp_min(1.0)
        return _Layers(*(v * (inv.unsqueeze(-1) if v.dim() == 2 else inv)
                         for v in (getattr(self, f.name) for f in fields(_Layers))))


@dataclass(frozen=True)
class _ChunkSums:
    """One chunk of sub-pixel rays: each ray's pixel and what it saw (summed into the view in chunk order)."""

    pixel: Int[Tensor, " R"]
    seen: _Layers


@torch.no_grad()   # grad mode is per thread: the worker threads need their own
def _render_chunk(model: NeFIIModel, geometry: Geometry, hit: SurfaceHit, d: Tensor, pixel: Tensor, c: Tensor,
                  per_ray: int, seed: int, transport: Transport) -> _ChunkSums:
    """The sub-pixel rays ``c`` (indices of hits), traced with a generator of their own seeded by ``seed``, so
    the result does not depend on which thread renders the chunk or when. ``per_ray = 0``: the material
    layers only (the colour layers are zero)."""
    pts = SurfacePoints.from_hit(hit, c, -d[c])
    material = decode_material(model, pts.position, pts.lookup_normal)
    cache = model.cache(pts.position, pts.normal, pts.wo)
    if per_ray == 0:
        zero = torch.zeros_like(cache)
        return _ChunkSums(pixel[c], _Layers(zero, zero, zero, material.albedo, pts.normal, cache, material.roughness))
    g = torch.Generator(device=d.device).manual_seed(seed)
    traced = path_trace(model, geometry, pts, material, per_ray, g, transport)
    return _ChunkSums(pixel[c], _Layers(traced.radiance.rgb, traced.radiance.specular, traced.radiance.diffuse,
                                        material.albedo, pts.normal, cache, material.roughness))


@dataclass(frozen=True)
class _Pass:
    """One set of sub-pixel rays through every pixel of a view and their sums per pixel."""

    sums: _Layers
    """``(P, ...)``: summed over each pixel's rays that hit"""
    hits: Float[Tensor, " P"]
    """rays of the pixel that hit the geometry"""
    centre_dirs: Float[Tensor, "P 3"]
    """the mean direction of the pixel's rays"""


@contextmanager
def _one_intra_op_thread() -> Iterator[None]:
    """Torch ops run on the calling thread only (restored afterwards): the chunks are the parallel work."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@torch.no_grad()
def render_view(model: NeFIIModel, geometry: Geometry, cameras: Cameras, view: int, num_samples: int,
                generator: torch.Generator | None, transport: Transport = Transport(), chunk: int = 512,
                workers: int | None = None, filtered_layers: bool = True) -> ViewPrediction:
    """``num_samples`` estimator samples per pixel, spread over its colour's sub-pixel rays (a single ray through
    the pixel centre when ``num_samples < 4``); the material layers and the mask read 4 x 4 rays a pixel at any
    ``num_samples`` (a second set of rays where the colour's are fewer), or the colour's rays where
    ``filtered_layers`` is false (a preview's). ``num_samples = 0``: the material layers only, no colour traced
    (``rgb``, ``specular`` and ``diffuse`` are None). ``chunk`` rays at a time: 512 keeps a chunk's (directions x 128
    lobes) tensors near the CPU's cache; 4096 took 1.2x as long a view at 256 spp on 2 threads.

    On the CPU the chunks are rendered by ``workers`` threads (default: torch's thread count), each running
    its torch ops single-threaded: a chunk's tensors are too small for intra-op threads to pay, so one
    process used about one core of two (docs/experiments.md, 2026-11-26). Every chunk draws from its own
    generator, seeded from ``generator``, and the chunks are summed in order: the result is the same for
    any number of workers."""
    if num_samples < 0:
        raise ValueError(f"num_samples: {num_samples} is negative")
    H, W = cameras.height, cameras.width
    device = next(model.parameters()).device
    k = subpixel_grid(num_samples)
    k_material = subpixel_grid(MAX_SUBPIXELS) if filtered_layers else k
    per_ray = max(1, num_samples // (k * k))
    workers = torch.get_num_threads() if workers is None else workers

    def one_pass(grid: int, samples: int) -> _Pass:
        n_px = H * W
        pixel, u = subpixel_samples(n_px, grid, generator, device)
        o, d = jittered_pixel_rays(cameras.c2w[view].to(device), cameras.K[view].to(device), W, pixel, u)
        o, d = o.float(), d.float()
        hit = geometry.intersect(Rays(o, d))
        chunks = hit.valid.nonzero().squeeze(-1).split(chunk)
        base = int(torch.randint(0, 2**62, (1,), generator=generator, device=device))

        def render(i: int) -> _ChunkSums:
            return _render_chunk(model, geometry, hit, d, pixel, chunks[i], samples, base + i, transport)

        if device.type == "cpu" and workers > 1 and len(chunks) > 1:
            with _one_intra_op_thread(), ThreadPoolExecutor(workers) as pool:
                results = list(pool.map(render, range(len(chunks))))
        else:
            results = [render(i) for i in range(len(chunks))]
        sums = _Layers.zeros(n_px, device)
        for r in results:
            sums.add_at(r.pixel, r.seen)
        hits = torch.zeros(n_px, device=device).index_add_(0, pixel, hit.valid.float())
        return _Pass(sums, hits, d.reshape(n_px, grid * grid, 3).mean(1))

    layers = one_pass(k_material, per_ray if k == k_material and num_samples > 0 else 0)
    material = layers.sums.divided(layers.hits)
    shape3 = (H, W, 3)
    rgb = specular = diffuse = None
    if num_samples > 0:
        colour = layers if k == k_material else one_pass(k, per_ray)
        seen = material if colour is layers else colour.sums.divided(colour.hits)
        on = colour.hits > 0
        rgb = torch.where(on.unsqueeze(-1), seen.rgb,
                          model.env.radiance(normalize(colour.centre_dirs))).reshape(shape3)
        specular, diffuse = seen.specular.reshape(shape3), seen.diffuse.reshape(shape3)
    return ViewPrediction(rgb=rgb, specular=specular, diffuse=diffuse, albedo=material.albedo.reshape(shape3),
                          roughness=material.roughness.reshape(H, W),
                          normal=torch.where((layers.hits > 0).unsqueeze(-1), normalize(material.normal),
                                             material.normal).reshape(shape3),
                          cache=material.cache.reshape(shape3),
                          mask=(layers.hits >= 0.5 * k_material * k_material).reshape(H, W))
