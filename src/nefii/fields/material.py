"""The material field ``M(x[, f]) -> (albedo, roughness)`` (paper Sec. 3.1)."""
from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..render.brdf import BRDFModel, Material, roughness_from_logit
from .encodings import FourierFeatures, HashGrid
from .features import FeatureField
from .mlp import mlp


class MaterialField(nn.Module):
    """Diffuse albedo ``sigmoid`` and roughness ``0.911 sigmoid + 0.089`` at world points
    (with ``features``, the frozen SDF's feature vector at the point is an input too).

    ``box`` = (lo, hi) corners of the scene's bounding box: points are mapped into ``[0,1]^3``
    before encoding. ``roughness_override`` (the warm-up policy's constant) replaces the
    learned roughness without touching its parameters.

    ``normal_offset`` (world units, 0: off) encodes the point ``x + normal_offset * n`` instead of
    ``x``, ``n`` the unit shading normal there. On a fixed surface this is only a change of
    coordinates (the albedo is still a function of the surface point), but the two faces of a
    thin wall, close together in space, are pushed apart by twice the offset, so they no
    longer share the encoding's coarse cells: without it a bowl's outside takes the colour of its
    inside and the light's lower hemisphere absorbs the difference.

    ``brdf``: the lobes the decoded parameters feed (carried by every :class:`Material` it returns).
    """

    def __init__(self, encoding: HashGrid | FourierFeatures, hidden: int, layers: int,
                 box: tuple[Tensor, Tensor], features: FeatureField | None = None, normal_offset: float = 0.0,
                 brdf: BRDFModel = BRDFModel()) -> None:
        super().__init__()
        self.brdf = brdf
        self.encoding, self.features, self.normal_offset = encoding, features, float(normal_offset)
        self.net = mlp(encoding.out_dim + (features.dim if features is not None else 0), 4, hidden, layers)
        self.register_buffer("box_lo", torch.as_tensor(box[0], dtype=torch.float32))
        self.register_buffer("box_size", torch.as_tensor(box[1], dtype=torch.float32) - self.box_lo)

    def forward(self, x: Float[Tensor, "*bs 3"], normal: Float[Tensor, "*bs 3"] | None = None,
                roughness_override: float | None = None) -> Material:
        """The material at surface points ``x`` with unit shading normals ``normal`` (needed when
        ``normal_offset`` > 0; the frozen SDF's features, if any, are read at ``x`` itself)."""
        x_enc = x
        if self.normal_offset > 0:
            if normal is None:
                raise ValueError("this material field encodes x + offset * n: pass the surface normals")
            x_enc = x + self.normal_offset * normal
        u = (x_enc - self.box_lo) / self.box_size
        h = self.encoding(u)
        if self.features is not None:
            h = torch.cat([h, self.features(x)], -1)
        out = self.net(h)
        albedo = torch.sigmoid(out[..., :3])
        if roughness_override is None:
            roughness = roughness_from_logit(out[..., 3])
        else:
            roughness = torch.full_like(out[..., 3], roughness_override)
        return Material(albedo, roughness, self.brdf)
