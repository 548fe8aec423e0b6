"""Procedural HDR environments: radiance as a function of world direction (Z up).

Each :class:`Environment` is a smooth ``background(d)`` (sky gradient, clouds, coloured
ground, horizon silhouettes, or a room with soft boxes) plus an optional :class:`Sun`, a
uniform disc added on top. The disc is kept apart so that bakers can integrate it exactly
over each texel instead of point-sampling a feature a few texels wide. None of it is a sum
of spherical Gaussians. Radiance is linear RGB; a white Lambertian surface facing up under
any of these reads roughly 0.5-0.9, so sRGB PNGs are well exposed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from jaxtyping import Float
from torch import Tensor

from .noise import noise2, smoothstep

Radiance = Callable[[Tensor], Tensor]
"""``(*bs, 3)`` unit directions -> ``(*bs, 3)`` linear RGB radiance"""


@dataclass(frozen=True)
class Sun:
    """A uniform disc of constant radiance."""

    direction: tuple[float, float, float]
    """unit vector towards the sun's centre"""
    radiance: tuple[float, float, float]
    """linear RGB radiance inside the disc"""
    angular_diameter_deg: float = 1.0

    @property
    def cos_radius(self) -> float:
        return math.cos(math.radians(0.5 * self.angular_diameter_deg))

    def solid_angle(self) -> float:
        return 2.0 * math.pi * (1.0 - self.cos_radius)


@dataclass(frozen=True)
class Environment:
    name: str
    description: str
    lighting: str
    """"hard sun" or "soft" """
    background: Radiance
    sun: Sun | None = None

    def radiance(self, d: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        """Point evaluation including the sun disc (the bakers integrate the disc instead)."""
        out = self.background(d)
        if self.sun is not None:
            inside = (d @ torch.tensor(self.sun.direction, dtype=d.dtype)) >= self.sun.cos_radius
            out = torch.where(inside.unsqueeze(-1), torch.tensor(self.sun.radiance, dtype=out.dtype), out)
        return out


# ---------------------------------------------------------------- pieces

def direction(elevation_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    """Unit vector at an elevation above the horizon and an azimuth from +X towards +Y."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))


def _c(*v: float) -> Tensor:
    return torch.tensor(v, dtype=torch.float32)


def _lerp(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    return a + (b - a) * w.unsqueeze(-1)


def sky_gradient(d: Tensor, zenith: Tensor, horizon: Tensor, exponent: float) -> Tensor:
    """Horizon colour fading to zenith colour as ``1 - (1 - z)^exponent``."""
    z = d[..., 2].clamp(0.0, 1.0)
    return _lerp(horizon, zenith, 1.0 - (1.0 - z) ** exponent)


def glow(d: Tensor, toward: tuple[float, float, float], width_deg: float) -> Tensor:
    """Gaussian falloff of the angle to ``toward`` (1 at the centre)."""
    cos = (d @ torch.tensor(toward, dtype=d.dtype)).clamp(-1.0, 1.0)
    ang = torch.acos(cos)
    return torch.exp(-0.5 * (ang / math.radians(width_deg)) ** 2)


def _plane(d: Tensor, sign: float, eps: float) -> Tensor:
    """Where the direction meets a horizontal plane one unit above (``sign`` 1) or below (-1)."""
    k = 1.0 / ((sign * d[..., 2]).clamp_min(0.0) + eps)
    return d[..., :2] * k.unsqueeze(-1)


def cloud_density(d: Tensor, cover: float, scale: float, seed: int, stretch: float = 1.0) -> Tensor:
    """Clouds on a flat layer above the viewer: noise of the layer point thresholded so that about
    ``cover`` of the layer is cloud; faded out towards the horizon."""
    q = _plane(d, 1.0, 0.08) * torch.tensor([scale * stretch, scale])
    n = noise2(q, seed)
    return smoothstep(1.0 - cover - 0.1, 1.0 - cover + 0.12, n) * smoothstep(0.0, 0.15, d[..., 2])


def cloud_shade(d: Tensor, scale: float, seed: int) -> Tensor:
    """Finer noise on the cloud layer for light and dark patches within clouds, in [0, 1]."""
    return noise2(_plane(d, 1.0, 0.08) * (3.0 * scale), seed)


def ground_pattern(d: Tensor, scale: float, seed: int) -> tuple[Tensor, Tensor]:
    """Fields seen below the horizon: two noises of the ground-plane point, in [0, 1]."""
    q = _plane(d, -1.0, 0.03) * scale
    return noise2(q, seed), noise2(q * 0.2, seed + 1)


def ridge_height(d: Tensor, base_deg: float, amp_deg: float, freq: float, seed: int) -> Tensor:
    """Elevation (radians) of a horizon silhouette, a periodic function of azimuth
    (``freq`` noise tiles around the horizon)."""
    phi = torch.atan2(d[..., 1], d[..., 0])
    x = (phi / (2.0 * math.pi) + 0.5) * round(freq)
    n = noise2(torch.stack([x, torch.full_like(x, 0.3)], -1), seed)
    return torch.deg2rad(base_deg + amp_deg * smoothstep(0.25, 1.0, n))


def silhouette(d: Tensor, height: Tensor) -> Tensor:
    """1 where the direction is above the horizon but below the silhouette ``height``."""
    elev = torch.asin(d[..., 2].clamp(-1.0, 1.0))
    return ((elev >= -1e-3) & (elev < height)).float()


def haze(d: Tensor, width: float) -> Tensor:
    """1 at the horizon, falling off as ``exp(-|z| / width)``."""
    return torch.exp(-d[..., 2].abs() / width)


# ---------------------------------------------------------------- presets

def outdoor(sky: Radiance, ground: Radiance) -> Radiance:
    """Evaluate ``sky`` only on directions with z >= 0 and ``ground`` only below the horizon."""
    def background(d: Tensor) -> Tensor:
        up = d[..., 2] >= 0
        out = torch.empty(d.shape, dtype=torch.float32)
        out[up] = sky(d[up])
        out[~up] = ground(d[~up])
        return out
    return background


def noon() -> Environment:
    sun = Sun(direction(52.0, 40.0), (12000.0, 11500.0, 10600.0))

    def sky(d: Tensor) -> Tensor:
        out = sky_gradient(d, _c(0.06, 0.13, 0.34), _c(0.36, 0.43, 0.53), 3.0)
        out = out + _c(0.35, 0.3, 0.22) * glow(d, sun.direction, 10.0).unsqueeze(-1)
        cd = cloud_density(d, 0.38, 1.2, seed=11) * (1.0 - glow(d, sun.direction, 14.0))
        shade = 0.7 + 0.5 * cloud_shade(d, 1.2, seed=12)
        out = _lerp(out, _c(0.95, 0.95, 0.97) * shade.unsqueeze(-1), cd)
        hills = _lerp(_c(0.06, 0.09, 0.07), _c(0.3, 0.36, 0.44), 0.5 * haze(d, 0.05))
        return _lerp(out, hills, silhouette(d, ridge_height(d, 0.5, 4.5, 3.0, seed=14)))

    def ground(d: Tensor) -> Tensor:
        g1, g2 = ground_pattern(d, 3.0, seed=13)
        out = _lerp(_lerp(_c(0.07, 0.11, 0.04), _c(0.16, 0.13, 0.07), smoothstep(0.4, 0.6, g2)),
                    _c(0.12, 0.15, 0.06), g1)
        return _lerp(out, _c(0.3, 0.34, 0.4), haze(d, 0.06))

    return Environment("noon", "clear midday sky with scattered clouds, green fields and wooded hills; "
                       "sun 52 deg up", "hard sun", outdoor(sky, ground), sun)


def sunset() -> Environment:
    sun = Sun(direction(8.0, -115.0), (12000.0, 6600.0, 2900.0))

    def sky(d: Tensor) -> Tensor:
        out = sky_gradient(d, _c(0.05, 0.085, 0.22), _c(0.8, 0.4, 0.17), 6.0)
        out = out + _c(1.3, 0.65, 0.22) * glow(d, sun.direction, 18.0).unsqueeze(-1)
        cd = cloud_density(d, 0.32, 0.7, seed=21, stretch=0.25) * (1.0 - glow(d, sun.direction, 4.0))
        lit = _c(0.35, 0.15, 0.17) + _c(1.8, 0.8, 0.5) * glow(d, sun.direction, 35.0).unsqueeze(-1)
        out = _lerp(out, lit, cd)
        far = silhouette(d, ridge_height(d, 0.8, 5.0, 2.0, seed=23))
        near = silhouette(d, ridge_height(d, 0.2, 2.5, 4.0, seed=24))
        out = _lerp(out, _c(0.09, 0.06, 0.09), far)
        return _lerp(out, _c(0.03, 0.022, 0.03), near)

    def ground(d: Tensor) -> Tensor:
        g1, _ = ground_pattern(d, 2.0, seed=22)
        out = _lerp(_c(0.04, 0.03, 0.025), _c(0.08, 0.055, 0.04), g1)
        return _lerp(out, _c(0.3, 0.15, 0.09), haze(d, 0.04))

    return Environment("sunset", "low orange sun 8 deg above a mountain range, streaky lit clouds, dark ground",
                       "hard sun", outdoor(sky, ground), sun)


def overcast() -> Environment:
    hidden_sun = direction(40.0, 150.0)

    def sky(d: Tensor) -> Tensor:
        cie = ((1.0 + 2.0 * d[..., 2]) / 3.0).unsqueeze(-1)  # CIE overcast sky luminance
        texture = 0.85 + 0.3 * cloud_density(d, 0.5, 0.8, seed=31)
        out = _c(1.05, 1.1, 1.15) * cie * texture.unsqueeze(-1)
        out = out * (1.0 + 0.6 * glow(d, hidden_sun, 22.0)).unsqueeze(-1)
        trees = _lerp(_c(0.04, 0.05, 0.04), _c(0.3, 0.32, 0.35), 0.4 * haze(d, 0.03))
        return _lerp(out, trees, silhouette(d, ridge_height(d, 1.0, 3.5, 3.0, seed=33)))

    def ground(d: Tensor) -> Tensor:
        g1, g2 = ground_pattern(d, 4.0, seed=32)
        out = _lerp(_c(0.07, 0.085, 0.06), _c(0.11, 0.1, 0.08), g1 * smoothstep(0.3, 0.7, g2))
        return _lerp(out, _c(0.35, 0.37, 0.4), haze(d, 0.05))

    return Environment("overcast", "fully overcast sky (CIE overcast gradient, cloud texture, brighter "
                       "where the sun hides), grey-green ground, tree line", "soft", outdoor(sky, ground))


def studio() -> Environment:
    half = torch.tensor([3.0, 2.5], dtype=torch.float32)
    floor_z, ceil_z = -1.2, 2.0

    def background(d: Tensor) -> Tensor:
        # first hit of the direction from the origin on the room's walls, floor or ceiling
        big = torch.full_like(d[..., 0], 1e9)
        tx = torch.where(d[..., 0].abs() > 1e-6, half[0] / d[..., 0].abs(), big)
        ty = torch.where(d[..., 1].abs() > 1e-6, half[1] / d[..., 1].abs(), big)
        tz = torch.where(d[..., 2] > 1e-6, ceil_z / d[..., 2].clamp_min(1e-6),
                         torch.where(d[..., 2] < -1e-6, floor_z / d[..., 2].clamp_max(-1e-6), big))
        t = torch.minimum(torch.minimum(tx, ty), tz)
        p = d * t.unsqueeze(-1)
        x, y, z = p.unbind(-1)
        height = ((z - floor_z) / (ceil_z - floor_z)).clamp(0, 1)
        wall = _c(0.2, 0.18, 0.16) * (0.55 + 0.45 * height).unsqueeze(-1)
        wall = wall * (0.9 + 0.2 * noise2(torch.stack([x + y, z], -1) * 0.3, seed=41)).unsqueeze(-1)
        planks = torch.remainder(x * 4.0, 1.0)
        wood = 0.7 + 0.3 * noise2(torch.stack([y * 0.05 + 0.37 * torch.floor(x * 4.0), x * 0.6], -1), seed=42)
        floor = _c(0.12, 0.07, 0.035) * (wood * (0.75 + 0.25 * smoothstep(0.0, 0.03, planks))).unsqueeze(-1)
        ceiling = _c(0.25, 0.25, 0.24).expand_as(d)
        out = torch.where((t == tz).unsqueeze(-1), torch.where((z > 0).unsqueeze(-1), ceiling, floor), wall)
        # two soft boxes on the ceiling
        for cx, cy in ((-0.9, 0.4), (1.0, -0.3)):
            box = ((t == tz) & (z > 0) & ((x - cx).abs() < 0.6) & ((y - cy).abs() < 0.4)).float()
            out = _lerp(out, _c(7.0, 6.8, 6.4), box)
        # a window with mullions in the -Y wall
        on_wall = (t == ty) & (y < 0)
        pane = on_wall & (x.abs() < 1.3) & (z > 0.0) & (z < 1.5)
        mullion = (torch.remainder(x + 1.3, 0.65) < 0.05) | ((z - 0.75).abs() < 0.03)
        sky = _lerp(_c(2.4, 2.7, 3.2), _c(1.6, 1.9, 2.5), (z / 1.5).clamp(0, 1))
        out = torch.where((pane & ~mullion).unsqueeze(-1), sky, out)
        return torch.where((pane & mullion).unsqueeze(-1), _c(0.05, 0.05, 0.05).expand_as(out), out)

    return Environment("studio", "indoor room: two ceiling soft boxes, a window with mullions, beige walls, "
                       "plank floor", "soft", background)


ENVIRONMENTS: dict[str, Callable[[], Environment]] = {
    "noon": noon, "sunset": sunset, "overcast": overcast, "studio": studio}
"""every built-in environment by name"""


def get_environment(name: str) -> Environment:
    return ENVIRONMENTS[name]()
