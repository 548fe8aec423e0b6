"""The learnable parts of the geometry stage: SDF network, colour network, NeuS sharpness, background.

Points are in normalised coordinates (the unit sphere holds the object, see
:mod:`nefii.sdf.normalization`).
"""
from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..fields.encodings import FourierFeatures, HashGrid
from ..fields.mlp import mlp


def encode_point(encoding: HashGrid | FourierFeatures, u: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs E"]:
    """``encoding`` of a normalised point: a hash grid reads the unit cube ``[0, 1]^3``, Fourier features ``u``."""
    return encoding(0.5 * (u + 1.0) if isinstance(encoding, HashGrid) else u)


class SDFNetwork(nn.Module):
    """``u -> (f(u), feature(u))``: signed distance and the geometric feature vector of the paper.

    ``f(u) = |u| - init_radius + g(u)`` where the last layer of ``g`` starts at zero: training
    starts from an exact sphere (the role of IDR/NeuS's geometric initialisation) whatever the
    encoding, and ``g`` learns the difference.
    """

    def __init__(self, encoding: HashGrid | FourierFeatures, hidden: int, layers: int, feature_dim: int,
                 init_radius: float = 0.5) -> None:
        super().__init__()
        self.encoding, self.feature_dim, self.init_radius = encoding, feature_dim, init_radius
        self.hashed = isinstance(encoding, HashGrid)
        levels = encoding.num_levels if self.hashed else 1
        self.register_buffer("level_weights", torch.ones(levels), persistent=False)
        self.net = mlp(encoding.out_dim + 3, 1 + feature_dim, hidden, layers)
        with torch.no_grad():
            last = self.net[-1]
            last.weight[0].zero_()
            last.bias[0] = 0.0

    def forward(self, u: Float[Tensor, "*bs 3"]) -> tuple[Float[Tensor, " *bs"], Float[Tensor, "*bs F"]]:
        h = encode_point(self.encoding, u)
        if self.hashed:
            h = (h.unflatten(-1, (len(self.level_weights), -1)) * self.level_weights.unsqueeze(-1)).flatten(-2)
        out = self.net(torch.cat([h, u], -1))
        sdf = u.norm(dim=-1) - self.init_radius + out[..., 0]
        return sdf, out[..., 1:]

    def set_active_levels(self, active: float | None) -> None:
        """Coarse to fine (Neuralangelo): hash-grid level ``l`` is weighted ``clamp(active - l, 0, 1)``,
        so only the coarse levels shape the surface at first; ``None`` turns every level on."""
        levels = torch.arange(len(self.level_weights), dtype=self.level_weights.dtype, device=self.level_weights.device)
        self.level_weights.copy_(torch.ones_like(levels) if active is None else (active - levels).clamp(0.0, 1.0))

    def sdf(self, u: Float[Tensor, "*bs 3"]) -> Float[Tensor, " *bs"]:
        return self(u)[0]

    def with_gradient(self, u: Float[Tensor, "*bs 3"], create_graph: bool
                      ) -> tuple[Float[Tensor, " *bs"], Float[Tensor, "*bs 3"], Float[Tensor, "*bs F"]]:
        """SDF, its gradient w.r.t. ``u`` (kept in the graph when ``create_graph``, for the eikonal
        loss) and the feature vector."""
        with torch.enable_grad():
            u = u.detach().requires_grad_(True)
            sdf, feat = self(u)
            (grad,) = torch.autograd.grad(sdf.sum(), u, create_graph=create_graph)
        if not create_graph:
            sdf, feat = sdf.detach(), feat.detach()
        return sdf, grad, feat


class ColorNetwork(nn.Module):
    """``(u, n, v, feature) -> RGB`` radiance (softplus: linear HDR, never negative): the view-dependent
    appearance NeuS needs to fit the images; discarded after the geometry stage.

    With ``encoding`` (an appearance encoding of its own), the colour's spatial detail (texture) need
    not pass through the SDF's feature vector: on a small SDF network a shared encoding lets texture
    bands bend the surface."""

    def __init__(self, feature_dim: int, hidden: int, layers: int, dir_freqs: int = 4,
                 encoding: HashGrid | FourierFeatures | None = None) -> None:
        super().__init__()
        self.dir_enc = FourierFeatures(3, dir_freqs)
        self.encoding = encoding
        extra = 0 if encoding is None else encoding.out_dim
        self.net = mlp(3 + 3 + self.dir_enc.out_dim + feature_dim + extra, 3, hidden, layers)

    def forward(self, u: Float[Tensor, "*bs 3"], n: Float[Tensor, "*bs 3"], v: Float[Tensor, "*bs 3"],
                feature: Float[Tensor, "*bs F"]) -> Float[Tensor, "*bs 3"]:
        parts = [u, n, self.dir_enc(v), feature]
        if self.encoding is not None:
            parts.append(encode_point(self.encoding, u))
        return nn.functional.softplus(self.net(torch.cat(parts, -1)))


class Sharpness(nn.Module):
    """NeuS's learnable inverse standard deviation ``s = exp(10 v)`` of the logistic density."""

    def __init__(self, init: float = 0.3) -> None:
        super().__init__()
        self.v = nn.Parameter(torch.tensor(float(init)))

    def forward(self) -> Tensor:
        return torch.exp(10.0 * self.v).clamp(1e-6, 1e6)


class Background(nn.Module):
    """NeRF++'s model of what lies outside the unit sphere: a point at distance ``r > 1`` is encoded by
    the inverted-sphere coordinates ``(x / r, 1 / r)``; density and colour (with the view direction)
    come from a small MLP on their Fourier features. Used when there are no masks to separate the
    object from its surroundings."""

    def __init__(self, hidden: int = 64, layers: int = 2, freqs: int = 6, dir_freqs: int = 4) -> None:
        super().__init__()
        self.pos_enc = FourierFeatures(4, freqs)
        self.dir_enc = FourierFeatures(3, dir_freqs)
        self.trunk = mlp(self.pos_enc.out_dim, hidden, hidden, layers)
        self.density = nn.Linear(hidden, 1)
        self.color = nn.Sequential(nn.Linear(hidden + self.dir_enc.out_dim, hidden // 2), nn.ReLU(),
                                   nn.Linear(hidden // 2, 3))

    def forward(self, o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], far: Float[Tensor, " R"], n: int,
                generator: torch.Generator | None = None, perturb: bool = True) -> Float[Tensor, "R 3"]:
        """Composited background radiance of each ray beyond the sphere (``far``: where it leaves it),
        with ``n`` samples uniform in inverse distance ``1/r`` from 1 towards 0."""
        R = o.shape[0]
        u = torch.arange(n, device=o.device, dtype=o.dtype)
        u = u + (torch.rand(R, n, generator=generator, device=o.device, dtype=o.dtype) if perturb else 0.5)
        inv_r = 1.0 - u / (n + 1)                                              # (R, n), decreasing 1 -> 0
        # distance along the ray to the sphere of radius r: o + t d with |.| = r, t >= far
        b = (o * d).sum(-1, keepdim=True)
        c = (o * o).sum(-1, keepdim=True)
        r = 1.0 / inv_r
        t = -b + (b * b - c + r * r).clamp_min(0).sqrt()
        t = torch.maximum(t, far.unsqueeze(-1))
        x = o.unsqueeze(1) + t.unsqueeze(-1) * d.unsqueeze(1)
        xr = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        h = self.trunk(self.pos_enc(torch.cat([xr, inv_r.unsqueeze(-1)], -1)))
        sigma = nn.functional.softplus(self.density(h).squeeze(-1) - 1.0)
        rgb = nn.functional.softplus(self.color(torch.cat([h, self.dir_enc(d).unsqueeze(1).expand(R, n, -1)], -1)))
        dt = torch.cat([t[:, 1:] - t[:, :-1], t.new_full((R, 1), 1e3)], -1)
        alpha = 1.0 - torch.exp(-sigma * dt.clamp_min(0) * 0.1)
        trans = torch.cumprod(torch.cat([alpha.new_ones(R, 1), 1 - alpha + 1e-7], -1), -1)[:, :-1]
        return ((alpha * trans).unsqueeze(-1) * rgb).sum(1)

