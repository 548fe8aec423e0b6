"""The radiance cache ``L(x, n, w_o[, f]) -> RGB`` (paper Eq. 4): outgoing radiance at surface points,
used as the incoming light of secondary rays that hit the object."""
from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

from .encodings import FourierFeatures, HashGrid
from .features import FeatureField
from .mlp import mlp


class RadianceCache(nn.Module):
    """Non-negative RGB radiance leaving ``x`` (normal ``n``) towards ``w_o``.

    The output is ``softplus``: linear for bright values, never negative, times ``radiance_unit`` (1 while a fit
    trains in its own unit of radiance; the unit of the images in a written model, :mod:`nefii.fit.units`).
    """

    def __init__(self, encoding: HashGrid | FourierFeatures, dir_freqs: int, hidden: int, layers: int,
                 box: tuple[Tensor, Tensor], features: FeatureField | None = None) -> None:
        super().__init__()
        self.encoding, self.features = encoding, features
        self.dir_encoding = FourierFeatures(3, dir_freqs)
        in_dim = encoding.out_dim + 2 * self.dir_encoding.out_dim + (features.dim if features is not None else 0)
        self.net = mlp(in_dim, 3, hidden, layers)
        self.register_buffer("box_lo", torch.as_tensor(box[0], dtype=torch.float32))
        self.register_buffer("box_size", torch.as_tensor(box[1], dtype=torch.float32) - self.box_lo)
        self.register_buffer("radiance_unit", torch.ones(()))

    @property
    def max_lobe_sharpness(self) -> float:
        """The sharpest spherical Gaussian of outgoing radiance the direction encoding can hold: a lobe of
        sharpness ``lambda`` is a Gaussian of ``1 / sqrt(lambda)`` radians, whose spectrum falls to ``e^-1`` at
        angular frequency ``sqrt(2 lambda)``; the encoding's highest is ``pi 2^(F-1)`` (F frequencies; 0: none)."""
        top = math.pi * 2.0 ** (self.dir_encoding.num_freqs - 1) if self.dir_encoding.num_freqs else 0.0
        return 0.5 * top * top

    def forward(self, x: Float[Tensor, "*bs 3"], n: Float[Tensor, "*bs 3"], wo: Float[Tensor, "*bs 3"]
                ) -> Float[Tensor, "*bs 3"]:
        parts = [self.encoding((x - self.box_lo) / self.box_size), self.dir_encoding(n), self.dir_encoding(wo)]
        if self.features is not None:
            parts.append(self.features(x))
        return self.radiance_unit * nn.functional.softplus(self.net(torch.cat(parts, -1)))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        state_dict.setdefault(prefix + "radiance_unit", torch.ones(()))   # models written before it existed
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
