"""The test split as ``nefii eval`` sees it, cast once: ``k x k`` stratified sub-pixel rays per pixel
(``nefii.evaluate.render_views.subpixel_samples``, the rays ``nefii eval`` averages) against the frozen mesh,
the pixels it scores (``eval_mask``) and the ground truth (``ground_truth``). Both systems' materials are
read at these hits, nefii's field by ``material_at`` at the hits' lookup normals, the peer's textures at the
hits' atlas UVs (:func:`hit_uv`), and averaged per pixel (:func:`scatter`), as the ground truth's layers
average each pixel's samples."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nefii.camera import jittered_pixel_rays
from nefii.data.material import barycentrics
from nefii.data.scene import SceneData
from nefii.evaluate.render_views import subpixel_grid, subpixel_samples
from nefii.evaluate.run import eval_mask, ground_truth
from nefii.evaluate.table1 import ViewArrays, mean_scores, view_scores
from nefii.raycast import Geometry, Rays
from nefii.synth.meshes import TriMesh

SUBPIXELS = subpixel_grid(16)
"""``k``: rays per pixel ``k x k``, as ``nefii eval`` at 16 spp or more"""


@dataclass(frozen=True)
class ViewHits:
    """One test view's sub-pixel rays where they hit the mesh."""

    valid: np.ndarray
    """(H, W) bool: at least half of the pixel's rays hit (``nefii eval``'s object mask)"""
    pixel: np.ndarray
    """(M,) int64: the flat pixel ``i W + j`` of each hit"""
    position: np.ndarray
    """(M, 3) float64"""
    triangle: np.ndarray
    """(M,) int64"""
    lookup_normal: np.ndarray
    """(M, 3) float32, where the material field is read (``SurfaceHit.lookup_normal``)"""


@dataclass(frozen=True)
class TestViews:
    hits: list[ViewHits]
    masks: list[np.ndarray]
    """(H, W) bool: the pixels ``nefii eval`` scores"""
    gt: list[ViewArrays]


def cast_test_views(scene: SceneData, geometry: Geometry, k: int = SUBPIXELS, seed: int = 0) -> TestViews:
    """``k x k`` sub-pixel rays (pixel centres when ``k == 1``) of every view of ``scene`` (its test split)
    against ``geometry``; the strata's jitter drawn from ``seed``."""
    generator = torch.Generator().manual_seed(seed)
    hits, masks, gt = [], [], []
    for v in range(len(scene)):
        pixel, u = subpixel_samples(scene.height * scene.width, k, generator, "cpu")
        o, d = jittered_pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], scene.width, pixel, u)
        hit = geometry.intersect(Rays(o.float(), d.float()))
        ok = hit.valid.numpy()
        count = np.bincount(pixel.numpy()[ok], minlength=scene.height * scene.width)
        hits.append(ViewHits((count >= 0.5 * k * k).reshape(scene.height, scene.width), pixel.numpy()[ok],
                             hit.position.numpy()[ok].astype(np.float64), hit.triangle_id.numpy()[ok],
                             hit.lookup_normal.numpy()[ok]))
        masks.append(eval_mask(scene, v, hits[-1].valid))
        gt.append(ground_truth(scene, v))
    return TestViews(hits, masks, gt)


def hit_uv(hits: ViewHits, mesh: TriMesh) -> np.ndarray:
    """Atlas UV ``(M, 2)`` of each hit: its barycentrics in its triangle (triangle ``k`` of the cast mesh is
    ``mesh.faces[k]``, the mesh split at the atlas seams) applied to the corners' UVs."""
    corners = mesh.faces[hits.triangle]
    w = barycentrics(torch.from_numpy(mesh.vertices[corners].astype(np.float64)),
                     torch.from_numpy(hits.position.astype(np.float64))).numpy()
    return np.einsum("mk,mkc->mc", w, mesh.uv[corners])


def scatter(hits: ViewHits, values: np.ndarray) -> np.ndarray:
    """Per-hit values into an ``(H, W[, C])`` image: each pixel the mean over its rays that hit, 0 where none
    does (as ``nefii eval`` writes)."""
    n = hits.valid.size
    flat = values.reshape(len(values), -1).astype(np.float64)
    sums = np.zeros((n, flat.shape[1]))
    np.add.at(sums, hits.pixel, flat)
    count = np.bincount(hits.pixel, minlength=n)
    mean = sums / np.maximum(count, 1)[:, None]
    return mean.astype(np.float32).reshape(hits.valid.shape + values.shape[1:])


def positions(views: TestViews) -> tuple[torch.Tensor, torch.Tensor]:
    """Every view's hit points and lookup normals, concatenated (for ``material_at``)."""
    return tuple(torch.from_numpy(np.concatenate([getattr(h, k) for h in views.hits]).astype(np.float32))
                 for k in ("position", "lookup_normal"))


def split_views(views: TestViews, values: np.ndarray) -> list[np.ndarray]:
    """Concatenated per-hit values back into per-view images."""
    ends = np.cumsum([len(h.position) for h in views.hits])[:-1]
    return [scatter(h, part) for h, part in zip(views.hits, np.split(values, ends))]


MATERIAL_KEYS = ("albedo_psnr", "albedo_ssim", "roughness_mse")


def material_scores(views: TestViews, albedo: list[np.ndarray], roughness: list[np.ndarray]) -> dict[str, float]:
    """Masked Table 1 material columns of per-view albedo ``(H, W, 3)`` and roughness ``(H, W)`` images."""
    per_view = [view_scores(ViewArrays(gt.rgb, a, r, None), ViewArrays(gt.rgb, gt.albedo, gt.roughness, None), m)[0]
                for gt, m, a, r in zip(views.gt, views.masks, albedo, roughness)]
    masked = mean_scores(per_view)["masked"]
    return {k: masked[k] for k in MATERIAL_KEYS}
