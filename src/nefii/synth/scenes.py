"""The built-in ground-truth scenes: procedural geometry, materials and lighting by name.

Every scene is made so that inter-reflection and shadowing matter: concave parts, objects
touching or leaning on each other, glossy next to rough, and base colour and roughness that
vary over each surface. There is no ground plane: objects float in their environment (or
stand on a finite plinth), so background pixels show the sky and masks are meaningful.
World Z is up; :func:`build_scene` centres the bounding box at the origin.
Materials are fixed per scene (no seed): a scene name always means the same ground truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from torch import Tensor

from . import meshes as M
from .noise import smoothstep
from .textures import Atlas, ProceduralMaterial, build_atlas, checker, dots, mix, noise, rgb, stripes, waves

Part = tuple[str, M.TriMesh, ProceduralMaterial]


@dataclass(frozen=True)
class SceneSpec:
    name: str
    summary: str
    """one line for ``nefii synth --list``"""
    environment: str
    """the environment the training and test views are lit by"""
    relight: tuple[str, str]
    """two other environments for the relighting ground truth"""
    elevation_deg: tuple[float, float]
    """camera elevations (above the object's centre) the views are spread over"""
    parts: Callable[[], list[Part]]


@dataclass(frozen=True)
class BuiltScene:
    spec: SceneSpec
    atlas: Atlas
    """merged world-space mesh (bounding box centred at the origin) and texture bitmaps"""
    radius: float
    """bounding-sphere radius about the origin"""


# ---------------------------------------------------------------- bowl (noon)

def _bowl_parts() -> list[Part]:
    Ri, Ro, zc, tm = 0.78, 0.84, 0.3, math.radians(68.0)
    rho = 0.5 * (Ro - Ri)
    m = np.array([0.5 * (Ro + Ri) * math.sin(tm), zc - 0.5 * (Ro + Ri) * math.cos(tm)])
    e_rad, e_t = np.array([math.sin(tm), -math.cos(tm)]), np.array([math.cos(tm), math.sin(tm)])
    t = np.linspace(0.0, tm, 28)
    a = np.linspace(0.0, math.pi, 11)
    rim = m[:, None] + rho * (np.cos(a) * e_rad[:, None] + np.sin(a) * e_t[:, None])
    profile = M.chain((Ro * np.sin(t), zc - Ro * np.cos(t)), (rim[0], rim[1]),
                      (Ri * np.sin(t[::-1]), zc - Ri * np.cos(t[::-1])))
    bowl = M.revolve([profile], 72)
    rb, tb = 0.26, math.radians(28.0)
    ball = M.sphere(rb, 20, 40).transformed(M.rotation((1, 0, 0), 0.4),
                                            ((Ri - rb) * math.sin(tb), 0.0, zc - (Ri - rb) * math.cos(tb)))

    def bowl_color(s: Tensor, t: Tensor) -> Tensor:
        inside = smoothstep(0.5, 0.53, t)
        clay = mix(rgb(0.5, 0.22, 0.1), rgb(0.62, 0.36, 0.2), noise(s, t, 2.0, 1))
        clay = mix(clay, rgb(0.2, 0.1, 0.06), stripes(t, 9.0, 0.12))
        glaze = mix(rgb(0.08, 0.3, 0.42), rgb(0.25, 0.55, 0.6), noise(s * 3, t, 1.5, 2))
        glaze = mix(glaze, rgb(0.85, 0.82, 0.75), smoothstep(0.78, 0.84, noise(s * 5, t * 1.5, 1.5, 3)))
        return mix(clay, glaze, inside)

    def bowl_rough(s: Tensor, t: Tensor) -> Tensor:
        inside = smoothstep(0.5, 0.53, t)
        return (0.8 - 0.15 * noise(s, t, 2.0, 4)) * (1 - inside) + (0.12 + 0.25 * noise(s * 3, t, 1.0, 5)) * inside

    def ball_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.82, 0.78, 0.62), rgb(0.6, 0.07, 0.05), dots(s, t, 8, 5, 0.28))

    def ball_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.7 - 0.5 * dots(s, t, 8, 5, 0.28)

    return [("bowl", bowl, ProceduralMaterial(bowl_color, bowl_rough)),
            ("ball", ball, ProceduralMaterial(ball_color, ball_rough))]


# ---------------------------------------------------------------- leaning (sunset)

def _rest(mesh: M.TriMesh, z: float = 0.0, x_max: float | None = None, gap: float = 1e-3) -> M.TriMesh:
    """Translate so the lowest point is at ``z`` (and the point furthest along +x at ``x_max``)."""
    v = mesh.vertices
    dx = 0.0 if x_max is None else x_max - gap - v[:, 0].max()
    return mesh.transformed(translation=(dx, 0.0, z + gap - v[:, 2].min()))


def _stone(seed: int) -> ProceduralMaterial:
    def color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.36, 0.35, 0.33), rgb(0.58, 0.56, 0.52), noise(s * 3, t, 2.0, seed))

    def rough(s: Tensor, t: Tensor) -> Tensor:
        tiles = checker(s, t, 12, 6)
        return 0.3 + 0.45 * tiles + 0.1 * noise(s, t, 3.0, seed + 1)

    return ProceduralMaterial(color, rough)


def _leaning_parts() -> list[Part]:
    plinth = M.rounded_slab(1.0, 0.08, 0.03, 128).transformed(translation=(0, 0, -0.04))
    bx, by, bz = 0.55, 0.7, 0.5
    box = M.box((bx, by, bz), 10).transformed(translation=(0.25, 0.0, bz / 2 + 1e-3))
    ring = M.torus(0.3, 0.08, 96, 32).transformed(M.rotation((0, 1, 0), math.radians(22))
                                                   @ M.rotation((1, 0, 0), math.pi / 2))
    ring = _rest(ring, 0.0, x_max=0.25 - bx / 2)
    ball = M.sphere(0.18, 24, 48).transformed(translation=(0.3, by / 2 + 0.181, 0.181))

    def wood(s: Tensor, t: Tensor) -> Tensor:
        grain = waves(s * 2, s + 0.3 * t, 14.0, 0.08, 11)
        return mix(rgb(0.42, 0.25, 0.12), rgb(0.24, 0.13, 0.06), grain)

    def wood_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.45 + 0.3 * noise(s, t, 2.0, 12) + 0.15 * checker(s, t, 3, 2)

    def ring_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.85, 0.8, 0.68), rgb(0.65, 0.08, 0.06), stripes(s, 10.0, 0.5))

    def ring_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.12 + 0.3 * stripes(s + 0.25, 10.0, 0.5)

    def ball_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.05, 0.3, 0.12), rgb(0.5, 0.7, 0.45), waves(s, t, 4.0, 0.3, 13))

    def ball_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.15 + 0.4 * noise(s, t, 2.0, 14)

    return [("plinth", plinth, _stone(15)), ("box", box, ProceduralMaterial(wood, wood_rough)),
            ("ring", ring, ProceduralMaterial(ring_color, ring_rough)),
            ("ball", ball, ProceduralMaterial(ball_color, ball_rough))]


# ---------------------------------------------------------------- cup (overcast)

def _cup_parts() -> list[Part]:
    R, th, lift = 0.75, 0.035, 0.09
    r = np.linspace(0.0, R, 30)
    top = lift * (r / R) ** 2
    rim = np.linspace(-math.pi / 2, math.pi / 2, 9)
    saucer = M.revolve([(r, top - th), (R + 0.5 * th * np.cos(rim), lift - 0.5 * th + 0.5 * th * np.sin(rim)),
                        (r[::-1], top[::-1])], 96)
    lip = np.linspace(0.0, math.pi, 9)
    cup = M.revolve([M.line((0.0, 0.0), (0.24, 0.0), 6), M.line((0.24, 0.0), (0.32, 0.55), 20),
                     (0.2975 + 0.0225 * np.cos(lip), 0.55 + 0.0225 * np.sin(lip)),
                     M.line((0.275, 0.55), (0.2, 0.06), 20), M.line((0.2, 0.06), (0.0, 0.06), 6)], 96)
    cup = cup.transformed(translation=(0.0, 0.0, lift * (0.24 / R) ** 2 + 1e-3))  # rests on its foot ring
    # handle: a torus section in the XZ plane, tilted with the flared wall, ends capped inside the wall
    sweep, ring_r, tube_r = 0.6 * math.pi, 0.15, 0.02
    tilt = M.rotation((0, 1, 0), -math.atan2(0.08, 0.55)) @ M.rotation((1, 0, 0), math.pi / 2)
    centre = np.array([0.31, 0.0, 0.31])
    handle = M.torus(ring_r, tube_r, 40, 16, (-sweep, sweep)).transformed(tilt, centre)
    caps = [M.sphere(tube_r, 8, 16).transformed(translation=centre + tilt @ (ring_r * np.array(
        [math.cos(a), math.sin(a), 0.0]))) for a in (-sweep, sweep)]
    handle = M.merge([handle] + caps)
    cube = M.box((0.12, 0.12, 0.12), 4).transformed(M.rotation((0, 0, 1), 0.5), (-0.3, 0.42, 0.06 + 0.03))

    def glaze(s: Tensor, t: Tensor) -> Tensor:
        band = stripes(t, 1.0, 0.12) + stripes(t - 0.16, 1.0, 0.04)
        c = mix(rgb(0.85, 0.84, 0.8), rgb(0.08, 0.15, 0.5), band.clamp(0, 1))
        return mix(c, rgb(0.1, 0.2, 0.55), dots(s * 2, t * 2, 16, 6, 0.2) * smoothstep(0.25, 0.3, t)
                   * (1 - smoothstep(0.45, 0.5, t)))

    def glaze_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.12 + 0.2 * noise(s, t, 2.0, 21) + 0.35 * smoothstep(0.6, 0.7, t)

    def saucer_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.8, 0.76, 0.68), rgb(0.55, 0.12, 0.1), checker(s, t, 16, 8))

    def saucer_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.2 + 0.5 * checker(s, t, 16, 8) * (0.7 + 0.3 * noise(s, t, 2.0, 22))

    def sugar(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.8, 0.8, 0.78), rgb(0.65, 0.62, 0.58), noise(s, t, 4.0, 23, 1.5))

    def sugar_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.85 + 0.0 * s

    cup_mat = ProceduralMaterial(glaze, glaze_rough)
    return [("saucer", saucer, ProceduralMaterial(saucer_color, saucer_rough)), ("cup", cup, cup_mat),
            ("handle", handle, ProceduralMaterial(lambda s, t: glaze(s, 0.05 + 0 * t), glaze_rough)),
            ("sugar", cube, ProceduralMaterial(sugar, sugar_rough))]


# ---------------------------------------------------------------- corner (studio)

def _corner_parts() -> list[Part]:
    w, th, h = 1.3, 0.08, 0.7
    floor = M.box((w, w, th), 12).transformed(translation=(0.0, 0.0, -th / 2))
    back = M.box((w, th, h), 10).transformed(translation=(0.0, w / 2 - th / 2, h / 2 + 1e-3))
    side = M.box((th, w - th, h), 10).transformed(translation=(-w / 2 + th / 2, -th / 2, h / 2 + 1e-3))
    rs = 0.25
    ball = M.sphere(rs, 32, 64).transformed(M.rotation((0, 1, 1), 0.7),
                                            (-w / 2 + th + rs + 2e-3, w / 2 - th - rs - 2e-3, rs + 2e-3))
    ring = M.torus(0.2, 0.06, 64, 24).transformed(translation=(0.3, -0.25, 0.061))
    cyl_profile = M.chain(M.line((0.0, 0.0), (0.1, 0.0), 5), M.arc(0.1, 0.02, 0.02, -math.pi / 2, 0.0, 5),
                          M.line((0.12, 0.02), (0.12, 0.43), 16), M.arc(0.0, 0.43, 0.12, 0.0, math.pi / 2, 12))
    column = M.revolve([cyl_profile], 64).transformed(translation=(0.3, 0.35, 1e-3))

    def tiles(s: Tensor, t: Tensor) -> Tensor:
        c = mix(rgb(0.82, 0.8, 0.76), rgb(0.08, 0.08, 0.09), checker(s, t, 18, 12))
        return mix(c, rgb(0.5, 0.48, 0.45), 0.3 * waves(s, t, 3.0, 0.4, 31) * checker(s, t, 18, 12))

    def tiles_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.15 + 0.5 * checker(s, t, 18, 12)

    def plaster(s: Tensor, t: Tensor) -> Tensor:
        c = mix(rgb(0.62, 0.48, 0.38), rgb(0.72, 0.6, 0.5), noise(s, t, 3.0, 32))
        return mix(c, rgb(0.2, 0.35, 0.3), stripes(t + 0.1, 4.0, 0.2))

    def plaster_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.9 - 0.65 * stripes(t + 0.1, 4.0, 0.2)

    def ball_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.7, 0.14, 0.05), rgb(0.85, 0.5, 0.1), noise(s * 2, t, 2.0, 33))

    def ball_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.1 + 0.35 * smoothstep(0.45, 0.65, noise(s * 2, t, 2.0, 34))

    def ring_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.1, 0.2, 0.6), rgb(0.75, 0.78, 0.82), stripes(s, 12.0, 0.3))

    def column_color(s: Tensor, t: Tensor) -> Tensor:
        return mix(rgb(0.8, 0.6, 0.1), rgb(0.3, 0.22, 0.05), stripes(t, 6.0, 0.25))

    def column_rough(s: Tensor, t: Tensor) -> Tensor:
        return 0.75 - 0.5 * stripes(t, 6.0, 0.25)

    wall = ProceduralMaterial(plaster, plaster_rough)
    return [("floor", floor, ProceduralMaterial(tiles, tiles_rough)), ("back wall", back, wall),
            ("side wall", side, wall), ("ball", ball, ProceduralMaterial(ball_color, ball_rough)),
            ("ring", ring, ProceduralMaterial(ring_color, lambda s, t: 0.35 + 0.2 * stripes(s, 12.0, 0.3))),
            ("column", column, ProceduralMaterial(column_color, column_rough))]


# ---------------------------------------------------------------- registry

SCENES: dict[str, SceneSpec] = {s.name: s for s in (
    SceneSpec("bowl", "glossy glazed bowl with a dotted ball resting inside, hard noon sun (smallest)",
              "noon", ("overcast", "sunset"), (-25.0, 75.0), _bowl_parts),
    SceneSpec("leaning", "striped glossy ring leaning on a wooden box, ball touching it, on a stone plinth; "
              "low sunset sun", "sunset", ("noon", "studio"), (-10.0, 70.0), _leaning_parts),
    SceneSpec("cup", "glazed cup with a handle on a checkered saucer, sugar cube; overcast sky",
              "overcast", ("noon", "sunset"), (-15.0, 70.0), _cup_parts),
    SceneSpec("corner", "ball in the corner of two plaster walls on a tiled floor, ring and column; "
              "indoor soft boxes", "studio", ("noon", "overcast"), (5.0, 70.0), _corner_parts),
)}
"""every built-in scene by name"""


def scene_names() -> list[str]:
    return list(SCENES)


def build_scene(name: str, texture_tile: int = 384) -> BuiltScene:
    """Geometry in world space (bounding box centred at the origin) with its texture atlas."""
    spec = SCENES[name]
    parts = spec.parts()
    allv = np.concatenate([p[1].vertices for p in parts])
    centre = 0.5 * (allv.min(0) + allv.max(0))
    parts = [(n, m.transformed(translation=-centre), mat) for n, m, mat in parts]
    atlas = build_atlas(parts, texture_tile)
    radius = float(np.linalg.norm(atlas.mesh.vertices, axis=-1).max())
    return BuiltScene(spec, atlas, radius)


@lru_cache(maxsize=None)
def triangle_count(name: str) -> int:
    return sum(len(p[1].faces) for p in SCENES[name].parts())


def smallest_scene() -> str:
    """The built-in scene with the fewest triangles (the one ``nefii demo`` renders)."""
    return min(SCENES, key=triangle_count)
