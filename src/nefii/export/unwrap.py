"""UV atlas of the frozen mesh by xatlas (PyPI ``xatlas``), fitted into one square texture.

xatlas splits the mesh into charts, flattens each and packs them; vertices on chart seams are
duplicated (``source`` names the original vertex). UVs come back in image convention, the one
glTF uses: ``u`` to the right, ``v`` down from the top-left corner, both in [0, 1].

xatlas cannot re-pack without recomputing the charts (the expensive part: ~20 s for 50k
triangles), so it runs once, as a single atlas at a texel density that fills about 60% of the
texture, and the atlas is then scaled to fit the texture's side; the padding asked for is
1.5x the wanted one, because that scale is 0.7-1.0 in practice.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Int

FILL = 0.6
"""chart area / texture area that the texel density aims at (xatlas packs 55-80% full)"""


@dataclass(frozen=True)
class UVAtlas:
    source: Int[np.ndarray, " V"]
    """original vertex of each atlas vertex"""
    faces: Int[np.ndarray, "F 3"]
    """triangles over the atlas vertices, in the input's order and winding"""
    uv: Float[np.ndarray, "V 2"]
    """(u right, v down) in [0, 1] of the texture; texel (i, j) is centred at ((j+.5)/S, (i+.5)/S)"""
    size: int
    """texture side S in texels"""


def padding_for(size: int) -> int:
    """Texels kept free around each chart: 4 up to 1024, 8 at 2048 (room for the 1.5-texel
    rings of ``bake.rasterise``, bilinear filtering and a few mip levels)."""
    return int(np.clip(size // 256, 4, 16))


def unwrap(vertices: np.ndarray, faces: np.ndarray, size: int, padding: int | None = None) -> UVAtlas:
    """Charts of ``(vertices, faces)`` packed into one ``size``-square atlas (see the module doc)."""
    import xatlas

    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    tri = v.astype(np.float64)[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1).sum()
    if not area > 0:
        raise ValueError("the mesh has no area to unwrap")
    pack = xatlas.PackOptions()
    pack.resolution = 0                       # one atlas, as large as the density makes it
    pack.texels_per_unit = float(math.sqrt(FILL / area) * size)
    pack.padding = math.ceil(1.5 * (padding_for(size) if padding is None else padding))
    pack.bilinear = True
    atlas = xatlas.Atlas()
    atlas.add_mesh(v, f)
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas made {atlas.atlas_count} atlases; expected one")
    source, tri_idx, uv = atlas[0]
    # xatlas normalises by the atlas's own width and height; fit its longer side to the texture
    uv = uv.astype(np.float64) * np.array([atlas.width, atlas.height]) / max(atlas.width, atlas.height)
    return UVAtlas(source.astype(np.int64), tri_idx.astype(np.int64).reshape(-1, 3), uv, size)
