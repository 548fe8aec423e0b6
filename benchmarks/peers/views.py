"""The test split as nefii's eval sees it, cast once, and textures looked up at its hits.

``nefii eval`` renders each test pixel along the ray through the pixel *centre*
(``nefii.camera.pixel_rays``), cast against the frozen mesh by ``MeshGeometry``, and scores the
material it finds there with ``nefii.evaluate.table1.view_scores``. A textured peer is scored the
same way: the hit's barycentric coordinates in its triangle give its atlas UV, and the texture
is read there with Mitsuba's own bitmap filter (bilinear, clamped), so the numbers are those of
the textures Mitsuba renders, seen through nefii's camera rays.

Texture convention (Mitsuba's ``bitmap`` and xatlas/glTF's): ``u`` right, ``v`` down from the
image's top-left, texel ``(i, j)`` centred at ``((j + .5) / W, (i + .5) / H)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nefii.camera import pixel_rays
from nefii.data.scene import SceneData
from nefii.evaluate.table1 import ViewArrays, mean_scores, view_scores
from nefii.export.unwrap import UVAtlas
from nefii.geometry import MeshGeometry, Rays


@dataclass(frozen=True)
class ViewHits:
    """One test view's pixel-centre rays where they hit the mesh."""

    valid: np.ndarray
    """(H, W) bool: the ray hits the mesh"""
    position: np.ndarray
    """(M, 3) float64 hit points of the valid pixels, row-major order"""
    triangle: np.ndarray
    """(M,) int64 triangle of each hit"""
    normal: np.ndarray
    """(M, 3) float32 unit shading normals of the hits"""


@dataclass(frozen=True)
class TestViews:
    """What scoring a material needs: hits, the mask nefii eval scores over, and the ground truth."""

    hits: list[ViewHits]
    masks: list[np.ndarray]
    """(H, W) bool per view, chosen as ``nefii eval`` does (GT mask, else the data's, else the hits)"""
    gt: list[ViewArrays]
    height: int
    width: int


def cast_test_views(scene: SceneData, geometry: MeshGeometry) -> TestViews:
    """Pixel-centre rays of every view of ``scene`` (its test split) against ``geometry``."""
    gt = scene.ground_truth
    hits, masks, arrays = [], [], []
    for v in range(len(scene)):
        o, d = pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], scene.height, scene.width)
        hit = geometry.intersect(Rays(o.reshape(-1, 3).float(), d.reshape(-1, 3).float()))
        valid = hit.valid.numpy()
        hits.append(ViewHits(valid.reshape(scene.height, scene.width), hit.position.numpy()[valid].astype(np.float64),
                             hit.triangle_id.numpy()[valid], hit.normal.numpy()[valid]))
        if gt is not None and gt.mask is not None:
            masks.append(gt.mask[v].numpy().astype(bool))
        elif scene.masks is not None:
            masks.append(scene.masks[v].numpy().astype(bool))
        else:
            masks.append(hits[-1].valid)
        arrays.append(ViewArrays(
            scene.images[v].numpy(),
            None if gt is None or gt.albedo is None else gt.albedo[v].numpy(),
            None if gt is None or gt.roughness is None else gt.roughness[v].numpy(),
            None if gt is None or gt.specular is None else gt.specular[v].numpy()))
    return TestViews(hits, masks, arrays, scene.height, scene.width)


# ---------------------------------------------------------------- textures at hits

def barycentrics(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``(M, 3)`` weights ``w`` with ``p = w0 a + w1 b + w2 c`` for points ``p`` on triangles ``abc``."""
    e1, e2, q = b - a, c - a, p - a
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    q1, q2 = (q * e1).sum(-1), (q * e2).sum(-1)
    det = np.maximum(d11 * d22 - d12 * d12, 1e-300)
    w1 = (d22 * q1 - d12 * q2) / det
    w2 = (d11 * q2 - d12 * q1) / det
    return np.stack([1.0 - w1 - w2, w1, w2], -1)


def hit_uv(hits: ViewHits, vertices: np.ndarray, faces: np.ndarray, atlas: UVAtlas) -> np.ndarray:
    """Atlas UV ``(M, 2)`` of each hit (``atlas.faces[k]`` is triangle ``k`` of ``faces``, split at seams)."""
    tri = hits.triangle
    a, b, c = (vertices[faces[tri, k]].astype(np.float64) for k in range(3))
    w = barycentrics(hits.position, a, b, c)
    return np.einsum("mk,mkc->mc", w, atlas.uv[atlas.faces[tri]])


def sample_bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``texture`` ``(S_h, S_w[, C])`` at ``uv`` ``(M, 2)`` as Mitsuba's bitmap reads it: bilinear
    between texel centres, indices clamped at the border."""
    h, w = texture.shape[:2]
    x, y = uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xs = np.clip(np.stack([x0, x0 + 1]), 0, w - 1)
    ys = np.clip(np.stack([y0, y0 + 1]), 0, h - 1)
    if texture.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    t = texture.astype(np.float64)
    top = t[ys[0], xs[0]] * (1 - fx) + t[ys[0], xs[1]] * fx
    bottom = t[ys[1], xs[0]] * (1 - fx) + t[ys[1], xs[1]] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def scatter(hits: ViewHits, values: np.ndarray) -> np.ndarray:
    """Per-hit values into an ``(H, W[, C])`` image, 0 where the ray misses (as nefii eval writes)."""
    out = np.zeros(hits.valid.shape + values.shape[1:], np.float32)
    out[hits.valid] = values
    return out


# ---------------------------------------------------------------- scores

MATERIAL_KEYS = ("albedo_psnr", "albedo_ssim", "roughness_mse")


def material_scores(views: TestViews, albedo: list[np.ndarray], roughness: list[np.ndarray]) -> dict[str, float]:
    """Masked Table 1 material columns (``view_scores`` per view, then ``mean_scores``) of per-view
    albedo ``(H, W, 3)`` and roughness ``(H, W)`` images; the colour columns are not computed."""
    per_view = []
    for gt, mask, a, r in zip(views.gt, views.masks, albedo, roughness):
        pred = ViewArrays(rgb=gt.rgb, albedo=a, roughness=r, specular=None)
        per_view.append(view_scores(pred, ViewArrays(gt.rgb, gt.albedo, gt.roughness, None), mask)[0])
    masked = mean_scores(per_view)["masked"]
    return {k: masked[k] for k in MATERIAL_KEYS}


def textures_at_views(views: TestViews, uvs: list[np.ndarray], base_color: np.ndarray,
                      roughness: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Albedo and roughness images of every test view from textures, at the hits' UVs."""
    albedo = [scatter(h, sample_bilinear(base_color, uv)) for h, uv in zip(views.hits, uvs)]
    rough = [scatter(h, sample_bilinear(roughness, uv)) for h, uv in zip(views.hits, uvs)]
    return albedo, rough


def positions(views: TestViews) -> tuple[torch.Tensor, torch.Tensor]:
    """Every view's hit points and shading normals, concatenated (for a field decoded at them)."""
    return tuple(torch.from_numpy(np.concatenate([getattr(h, k) for h in views.hits]).astype(np.float32))
                 for k in ("position", "normal"))


def split_views(views: TestViews, values: np.ndarray) -> list[np.ndarray]:
    """Concatenated per-hit values back into per-view images."""
    out, k = [], 0
    for h in views.hits:
        n = len(h.position)
        out.append(scatter(h, values[k:k + n]))
        k += n
    return out
