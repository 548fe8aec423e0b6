"""First hits of every training pixel, cast once and cached (secondary rays are cast every step)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from ..camera import jittered_pixel_rays, pixel_rays
from ..config_tools import check_memory, host_memory_bytes
from ..data.scene import SceneData
from ..errors import InputError
from ..raycast.base import Geometry, Rays
from .path_trace import SurfacePoints


@dataclass(frozen=True)
class Pixels:
    """Object pixels at their first hits with their colours, and background pixels with their view
    directions and colours: all training pixels (:func:`first_hits`) or a batch of them (:meth:`select`)."""

    points: SurfacePoints
    rgb: Float[Tensor, "P 3"]
    """linear colour of the object pixels"""
    bg_dirs: Float[Tensor, "Q 3"]
    """view-ray directions of background pixels (they see the environment directly)"""
    bg_rgb: Float[Tensor, "Q 3"]
    view: Int[Tensor, "P"]
    """the training view each object pixel is from"""
    bg_view: Int[Tensor, "Q"]
    """the training view each background pixel is from"""
    footprint: SurfacePoints
    """(F P) the object pixels' hits at the :data:`FOOTPRINT_GRID` positions, position-major (``k P + i``: position
    ``k`` of pixel ``i``); where a position's ray misses the geometry, the pixel's centre hit stands in"""
    footprint_sky: Bool[Tensor, "FP"]
    """where a position's ray misses the geometry and the background is visible: that part of the pixel sees the
    environment along the ray (the row's ``wo`` is minus the ray's direction; its point is the centre hit's)"""
    edge: Bool[Tensor, "P"]
    """pixels the silhouette crosses where the background is visible: their colour mixes object and environment"""

    def select(self, obj: Tensor, bg: Tensor) -> "Pixels":
        """The object pixels ``obj`` and background pixels ``bg`` (index tensors)."""
        k = torch.arange(len(FOOTPRINT_GRID), device=obj.device)
        at = (k[:, None] * len(self.points) + obj[None]).reshape(-1)
        return Pixels(self.points[obj], self.rgb[obj], self.bg_dirs[bg], self.bg_rgb[bg], self.view[obj],
                      self.bg_view[bg], self.footprint[at], self.footprint_sky[at], self.edge[obj])

    def at_footprint(self, k: Int[Tensor, "P"]) -> tuple[SurfacePoints, Bool[Tensor, "P"]]:
        """Each object pixel ``i``'s hit at footprint position ``k[i]``, and whether that position sees the sky."""
        at = k * len(self.points) + torch.arange(len(self.points), device=k.device)
        return self.footprint[at], self.footprint_sky[at]

    @property
    def solid(self) -> Bool[Tensor, "P"]:
        """The object pixels the silhouette does not cross (all of them where the background is not visible): one
        surface's shading, what the light's start, the light solve, the radiance unit and the cache's term read."""
        return ~self.edge

    def without_edges(self) -> "Pixels":
        """The :attr:`solid` object pixels and every background pixel."""
        return self.select(self.solid.nonzero()[:, 0], torch.arange(len(self.bg_dirs), device=self.edge.device))

    def scaled(self, k: float) -> "Pixels":
        """The same pixels with every colour (object and background) times ``k``."""
        return dataclasses.replace(self, rgb=self.rgb * k, bg_rgb=self.bg_rgb * k)

    def to(self, device: torch.device | str) -> "Pixels":
        return Pixels(self.points.map(lambda t: t.to(device)), self.rgb.to(device), self.bg_dirs.to(device),
                      self.bg_rgb.to(device), self.view.to(device), self.bg_view.to(device),
                      self.footprint.map(lambda t: t.to(device)), self.footprint_sky.to(device), self.edge.to(device))


def view_rays(scene: SceneData, view: int) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 3"]]:
    """Float32 origins and unit directions of every pixel of one view (OpenCV cameras)."""
    o, d = pixel_rays(scene.cameras.c2w[view], scene.cameras.K[view], scene.height, scene.width)
    return o.float(), d.float()


FOOTPRINT_GRID = ((0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))
"""where in a pixel (fractions of its width and height) the fit's rays start: the centres of a 2 x 2 grid over
it. Each ground-truth pixel averages its whole footprint; one ray through its centre sees one normal where a
curved surface's pixel spans several degrees, and a sharp highlight spread over the pixel is then matched only
by a rougher lobe (docs/experiments.md, 2026-11-27, sixth session)"""

FOOTPRINT = ((0.05, 0.05), (0.95, 0.05), (0.05, 0.95), (0.95, 0.95))
"""where in a pixel (fractions of its width and height) its footprint is probed besides the centre"""


def rays_at(scene: SceneData, view: int, pixel: Int[Tensor, "P"], u: tuple[float, float]) -> Rays:
    """Float32 rays of ``view`` through position ``u`` (fractions of a pixel's width and height) of the flat
    pixels ``pixel``."""
    o, d = jittered_pixel_rays(scene.cameras.c2w[view], scene.cameras.K[view], scene.width, pixel,
                               torch.tensor(u, dtype=torch.float64).expand(len(pixel), 2))
    return Rays(o.float(), d.float())


def footprint_hits(scene: SceneData, geometry: Geometry, view: int) -> Bool[Tensor, "K HW"]:
    """Whether rays near each corner of every pixel of ``view`` hit the geometry (one row per corner of
    :data:`FOOTPRINT`)."""
    pixel = torch.arange(scene.height * scene.width)
    return torch.stack([geometry.intersect(rays_at(scene, view, pixel, u)).valid for u in FOOTPRINT])


def first_hits(scene: SceneData, geometry: Geometry) -> Pixels:
    """Cast every pixel once. Object pixels: the centre ray hits the mesh (and the mask, if any, says object).
    Background pixels: no hit (and the mask, if any, says background), and only where the background is visible at
    all (not for transparent RGBA renders). Where the background is visible, an object pixel the geometry's
    silhouette crosses (rays near its corners disagree with its centre, or a footprint ray misses) is an edge pixel:
    its colour mixes object and environment, and the fit renders it as that mixture (:attr:`Pixels.footprint_sky`);
    a background pixel the silhouette crosses is left out (a transparent render's edge pixels hold the object's
    colour alone: nothing of them sees the sky). Left out of both: pixels where mask and geometry disagree
    (silhouette errors, anti-aliased edges), and clipped pixels (their true colour is unknown: fitting them as if
    the scene were that bright would darken a sun's highlight)."""
    pts, rgb, bg_d, bg_c, views, bg_views, objs, crossed = [], [], [], [], [], [], [], []
    for v in range(len(scene)):
        o, d = view_rays(scene, v)
        hit = geometry.intersect(Rays(o.reshape(-1, 3), d.reshape(-1, 3)))
        colour = scene.images[v].reshape(-1, 3)
        obj, bg = hit.valid, ~hit.valid & scene.background_visible
        cross = torch.zeros_like(obj)
        if scene.background_visible:  # a pixel the silhouette crosses mixes object and background colour
            corners = footprint_hits(scene, geometry, v)
            cross, bg = ~corners.all(0), bg & ~corners.any(0)
        if scene.masks is not None:
            m = scene.masks[v].reshape(-1)
            obj, bg = obj & m, bg & ~m
        if scene.clipped is not None:
            keep = ~scene.clipped[v].reshape(-1)
            obj, bg = obj & keep, bg & keep
        dirs = d.reshape(-1, 3)
        centre = SurfacePoints.from_hit(hit, obj, -dirs[obj])
        pts.append(centre)
        objs.append(obj)
        crossed.append(cross[obj])
        rgb.append(colour[obj])
        bg_d.append(dirs[bg])
        bg_c.append(colour[bg])
        views.append(torch.full((int(obj.sum()),), v, dtype=torch.long))
        bg_views.append(torch.full((int(bg.sum()),), v, dtype=torch.long))
    total = sum(len(c) for c in pts)
    if total == 0:
        raise InputError(scene.root, "no training pixel sees the geometry: do the cameras, masks and mesh agree?")
    per_point = sum(getattr(pts[0], f.name).shape[1:].numel() * getattr(pts[0], f.name).element_size()
                    for f in fields(SurfacePoints))
    try:    # the footprint, the centre hits and their concatenation, all on the host
        check_memory((len(FOOTPRINT_GRID) + 2) * total * per_point, f"the first hits of {total} object pixels",
                     "the number or size of the training images (--set max_image_side=N)", have=host_memory_bytes())
    except ValueError as e:
        raise InputError(scene.root, str(e)) from None
    footprint, sky = _footprint(scene, geometry, objs, pts)
    edge = torch.cat(crossed) | sky.reshape(len(FOOTPRINT_GRID), total).any(0)
    return Pixels(SurfacePoints.cat(pts), torch.cat(rgb), torch.cat(bg_d), torch.cat(bg_c), torch.cat(views),
                  torch.cat(bg_views), footprint, sky, edge)


def background_clipping(scene: SceneData, geometry: Geometry) -> tuple[Float[Tensor, "Q 3"], Bool[Tensor, " Q"]] | None:
    """Every background pixel's view direction, clipped ones included, and whether it is clipped (what
    :func:`nefii.fit.light_init.sky_sun` reads); None where no background shows or nothing is clipped."""
    if not scene.background_visible or scene.clipped is None:
        return None
    dirs, clipped = [], []
    for v in range(len(scene)):
        o, d = view_rays(scene, v)
        hit = geometry.intersect(Rays(o.reshape(-1, 3), d.reshape(-1, 3)))
        bg = ~hit.valid if scene.masks is None else ~hit.valid & ~scene.masks[v].reshape(-1)
        dirs.append(d.reshape(-1, 3)[bg])
        clipped.append(scene.clipped[v].reshape(-1)[bg])
    return torch.cat(dirs), torch.cat(clipped)


def _footprint(scene: SceneData, geometry: Geometry, objs: list[Bool[Tensor, "HW"]],
               centres: list[SurfacePoints]) -> tuple[SurfacePoints, Bool[Tensor, "FP"]]:
    """:attr:`Pixels.footprint` and :attr:`Pixels.footprint_sky` of all views: written view by view into tensors
    allocated once, since the per-view pieces and their concatenation would hold it twice over (on a 100-view
    512 x 512 capture the footprint is 2 GiB)."""
    F, total, start = len(FOOTPRINT_GRID), sum(len(c) for c in centres), 0
    out = centres[0].map(lambda t: t.new_empty((F * total, *t.shape[1:])))
    sky = torch.zeros(F * total, dtype=torch.bool)
    for v, (obj, centre) in enumerate(zip(objs, centres)):
        for k, u in enumerate(FOOTPRINT_GRID):
            part, missed = _grid_hits(scene, geometry, v, obj, centre, u)
            at = slice(k * total + start, k * total + start + len(centre))
            for f in fields(SurfacePoints):
                getattr(out, f.name)[at] = getattr(part, f.name)
            sky[at] = missed & scene.background_visible
        start += len(centre)
    return out, sky


def _grid_hits(scene: SceneData, geometry: Geometry, view: int, obj: Bool[Tensor, "HW"], centre: SurfacePoints,
               u: tuple[float, float]) -> tuple[SurfacePoints, Bool[Tensor, "P"]]:
    """The hits of the rays through position ``u`` of the object pixels ``obj`` of ``view``, with ``centre``
    (their centre hits) standing in where such a ray misses, seen along the ray; and which rays missed."""
    rays = rays_at(scene, view, obj.nonzero()[:, 0], u)
    hit = geometry.intersect(rays)
    at, keep = SurfacePoints.from_hit(hit, slice(None), -rays.directions), hit.valid.unsqueeze(-1)
    stand_in = dataclasses.replace(centre, wo=-rays.directions) if scene.background_visible else centre
    return SurfacePoints(*(torch.where(keep, getattr(at, f.name), getattr(stand_in, f.name))
                           for f in fields(SurfacePoints))), ~hit.valid
