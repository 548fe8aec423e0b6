"""The frozen SDF's geometric feature vector ``f(x)`` as an input of the material and cache fields
(paper Sec. 3.1: ``M(x, f)`` and ``L(x, n, w, f)``). ``f`` is a function of position, so the fields
look it up themselves and every consumer (fit, eval, relight, export) evaluates them the same way."""
from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..sdf.networks import SDFNetwork


class FeatureField(nn.Module):
    """``x (world) -> f``: the SDF network's feature output at ``(x - center) / radius``, no gradient."""

    def __init__(self, sdf: SDFNetwork, center: tuple[float, float, float], radius: float) -> None:
        super().__init__()
        self.sdf = sdf.requires_grad_(False)
        self.register_buffer("center", torch.tensor(center, dtype=torch.float32))
        self.radius = float(radius)

    @property
    def dim(self) -> int:
        return self.sdf.feature_dim

    def forward(self, x: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs F"]:
        with torch.no_grad():
            return self.sdf((x - self.center) / self.radius)[1]
