"""Equirectangular environment maps as light: radiance lookup and piecewise-constant 2D
importance sampling (PBRT's ``Distribution2D``) in the mapping of :mod:`nefii.render.equirect`.

The density is proportional to luminance times ``sin(theta)`` of each pixel's centre row (the
pixel's solid angle), with a small floor so every direction can be sampled. Within a pixel,
``(u, v)`` is uniform, so the density over solid angle is exactly
``p(w) = p_uv(u, v) / (2 pi^2 sin(theta))``: the one this sampler draws from.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from .equirect import direction_to_uv, uv_to_direction

LUMINANCE = (0.2126, 0.7152, 0.0722)


def envmap_lookup(image: Float[Tensor, "H W 3"], w: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """Radiance of the pixel each direction falls in (piecewise constant, differentiable in ``image``)."""
    H, W = image.shape[:2]
    u, v = direction_to_uv(w)
    col = (u * W).long().clamp(0, W - 1)
    row = (v * H).long().clamp(0, H - 1)
    return image.reshape(-1, 3)[row * W + col]


@dataclass(frozen=True)
class EnvmapDistribution:
    """Sampling tables of one map (no gradient)."""

    row_cdf: Float[Tensor, " Hp1"]
    """(H+1,) marginal CDF over rows, from 0 to 1"""
    col_cdf: Float[Tensor, "H Wp1"]
    """(H, W+1) conditional CDFs over columns of each row"""
    p_uv: Float[Tensor, "H W"]
    """density over the unit square (u, v) of each pixel"""
    col_cdf_shifted: Float[Tensor, " HWp1"]
    """float64 ``col_cdf + row index``, flattened: all rows' CDFs as one increasing sequence"""

    @property
    def shape(self) -> tuple[int, int]:
        return self.p_uv.shape[0], self.p_uv.shape[1]


def _cdf(f: Tensor) -> Tensor:
    c = torch.cumsum(f, -1)
    c = c / c[..., -1:].clamp_min(1e-30)
    return torch.cat([torch.zeros_like(c[..., :1]), c], -1)


@torch.no_grad()
def build_envmap_distribution(image: Float[Tensor, "H W 3"], floor: float = 1e-3) -> EnvmapDistribution:
    """Tables for sampling ``image``; ``floor`` (relative to the mean luminance) keeps dark pixels reachable."""
    H, W = image.shape[:2]
    lum = (image.clamp_min(0) * torch.tensor(LUMINANCE, dtype=image.dtype, device=image.device)).sum(-1)
    lum = lum + floor * lum.mean().clamp_min(1e-12)
    theta = (torch.arange(H, dtype=image.dtype, device=image.device) + 0.5) * (math.pi / H)
    f = lum * torch.sin(theta).unsqueeze(-1)                                   # (H, W)
    row_sum = f.sum(-1)
    total = row_sum.sum()
    p_uv = f / total * (H * W)
    col_cdf = _cdf(f)
    shifted = (col_cdf.double() + torch.arange(H, device=image.device, dtype=torch.float64).unsqueeze(-1)).reshape(-1)
    return EnvmapDistribution(row_cdf=_cdf(row_sum), col_cdf=col_cdf, p_uv=p_uv, col_cdf_shifted=shifted)


def _sample_cdf(cdf: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Bin index and continuous offset in [0, 1) within it, for one CDF ``(n+1,)`` and any ``u``."""
    n = cdf.shape[-1] - 1
    idx = (torch.searchsorted(cdf, u.contiguous(), right=True) - 1).clamp(0, n - 1)
    lo, hi = cdf[idx], cdf[idx + 1]
    off = ((u - lo) / (hi - lo).clamp_min(1e-30)).clamp(0.0, 1.0 - 1e-7)
    return idx, off


def _sample_row_cdfs(cdfs: Tensor, shifted: Tensor, row: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """As :func:`_sample_cdf` in the CDF ``cdfs[row]`` of each sample (``cdfs``: ``(H, n+1)``).

    One search in ``shifted``, the concatenation of all rows each shifted by its row index
    (float64, so the shift keeps full precision): no per-sample copy of a row.
    """
    H, n1 = cdfs.shape
    key = row.double() + u.double()
    pos = torch.searchsorted(shifted, key.contiguous(), right=True) - 1
    idx = (pos - row * n1).clamp(0, n1 - 2)
    a, b = cdfs[row, idx], cdfs[row, idx + 1]
    off = ((u - a) / (b - a).clamp_min(1e-30)).clamp(0.0, 1.0 - 1e-7)
    return idx, off


def sample_envmap(dist: EnvmapDistribution, u: Float[Tensor, "*bs 2"]) -> Float[Tensor, "*bs 3"]:
    """A direction with density :func:`pdf_envmap` from uniform ``u``."""
    H, W = dist.shape
    bs = u.shape[:-1]
    u = u.reshape(-1, 2)
    row, off_v = _sample_cdf(dist.row_cdf, u[:, 0])
    col, off_u = _sample_row_cdfs(dist.col_cdf, dist.col_cdf_shifted, row, u[:, 1])
    uu = (col.to(u.dtype) + off_u) / W
    vv = (row.to(u.dtype) + off_v) / H
    return uv_to_direction(uu, vv).reshape(*bs, 3)


def pdf_envmap(dist: EnvmapDistribution, w: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs"]:
    """Density over solid angle: ``p_uv / (2 pi^2 sin(theta))`` (0 at the poles' singular points)."""
    H, W = dist.shape
    u, v = direction_to_uv(w)
    col = (u * W).long().clamp(0, W - 1)
    row = (v * H).long().clamp(0, H - 1)
    sin_t = torch.hypot(w[..., 0], w[..., 1]) / w.norm(dim=-1)
    p = dist.p_uv[row, col] / (2.0 * math.pi**2 * sin_t.clamp_min(1e-12))
    return torch.where(sin_t > 0, p, torch.zeros_like(p))


# --------------------------------------------------------------------------- the light

SAMPLE_CHUNK_NUMBERS = 1 << 23
"""CDF entries held at once while sampling directions (32 MiB in float32)"""



def rotate_z(w: Float[Tensor, "*bs 3"], degrees: float) -> Float[Tensor, "*bs 3"]:
    """Turn directions about world +Z by ``degrees``, counter-clockwise seen from above."""
    if degrees == 0.0:
        return w
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    x, y, z = w.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], -1)


@dataclass(frozen=True)
class Environment:
    """An equirectangular map as light: radiance, importance sampling and its pdf, turned by ``rotation``.

    It is also a :class:`nefii.render.lights.LightSampler` (``sample(n, u)``, ``pdf(n, wi)``; ``n``
    is ignored), so the one-bounce estimator can use it.
    """

    image: Float[Tensor, "H W 3"]
    """linear radiance in the map's own frame, exposure applied"""
    dist: EnvmapDistribution
    """piecewise-constant 2D sampling tables of ``image`` (``nefii.render.envmap``)"""
    rotation: float = 0.0
    """degrees about world +Z, counter-clockwise seen from above"""

    @staticmethod
    def from_image(image: Float[Tensor, "H W 3"], rotation: float = 0.0) -> "Environment":
        return Environment(image, build_envmap_distribution(image), float(rotation))

    def radiance(self, w: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        """``E(w)``: the pixel ``R_z(-rotation) w`` falls in."""
        return envmap_lookup(self.image, rotate_z(w, -self.rotation))

    def sample_direction(self, u: Float[Tensor, "*bs 2"]) -> Float[Tensor, "*bs 3"]:
        """A world direction with density :meth:`pdf_direction` (rotations keep solid angle).

        ``sample_envmap`` holds a row of each CDF per sample (``H + W`` numbers), so large maps are
        sampled in chunks of about ``SAMPLE_CHUNK_NUMBERS / (H + W)`` directions to bound memory.
        """
        H, W = self.dist.shape
        flat = u.reshape(-1, 2)
        step = max(256, SAMPLE_CHUNK_NUMBERS // (H + W + 2))
        w = torch.cat([sample_envmap(self.dist, c) for c in flat.split(step)]) if len(flat) else flat.new_zeros(0, 3)
        return rotate_z(w.reshape(*u.shape[:-1], 3), self.rotation)

    def pdf_direction(self, w: Float[Tensor, "*bs 3"]) -> Float[Tensor, " *bs"]:
        return pdf_envmap(self.dist, rotate_z(w, -self.rotation))

    # LightSampler protocol (the estimator's light strategy)
    def sample(self, n: Tensor, u: Tensor) -> Tensor:
        return self.sample_direction(u[..., :2])

    def pdf(self, n: Tensor, wi: Tensor) -> Tensor:
        return self.pdf_direction(wi)
