"""Input encodings for the fields.

* :class:`FourierFeatures`: the paper's positional encoding (NeRF): ``[x, sin(2^k pi x), cos(2^k pi x)]``.
* :class:`HashGrid`: a multiresolution hash grid (Mueller et al. 2022) in pure PyTorch, the fast
  option for the CPU. Positions are expected in ``[0, 1]^3`` (the fields normalise by the scene box).
"""
from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

from .hashgrid_cpu import fused_encode


class FourierFeatures(nn.Module):
    """``x -> [x, sin(2^k pi x), cos(2^k pi x)]_{k < num_freqs}`` per coordinate."""

    def __init__(self, in_dim: int, num_freqs: int, include_input: bool = True) -> None:
        super().__init__()
        self.in_dim, self.num_freqs, self.include_input = in_dim, num_freqs, include_input
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(num_freqs, dtype=torch.float32), persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.num_freqs + int(self.include_input))

    def forward(self, x: Float[Tensor, "*bs D"]) -> Float[Tensor, "*bs E"]:
        xf = (x.unsqueeze(-1) * self.freqs.to(x.dtype)).flatten(-2)
        parts = [x] if self.include_input else []
        return torch.cat(parts + [torch.sin(xf), torch.cos(xf)], -1)


_PRIMES = (1, 2654435761, 805459861)


class _Gather(torch.autograd.Function):
    """``table[idx]`` whose backward is one ``index_add_`` (faster on CPU than embedding's backward).

    A row of two float32 features is read as one float64 (the same 8 bytes): one load per corner
    instead of a strided pair, about twice as fast on the CPU; the values are the same bits."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor) -> Tensor:
        ctx.save_for_backward(idx)
        ctx.table_shape = table.shape
        flat = idx.reshape(-1)
        if table.shape[-1] == 2 and table.dtype == torch.float32 and table.is_contiguous():
            rows = table.view(torch.float64).view(-1).index_select(0, flat).view(torch.float32)
        else:
            rows = table.index_select(0, flat)
        return rows.view(*idx.shape, table.shape[-1])

    @staticmethod
    def backward(ctx, grad: Tensor):
        (idx,) = ctx.saved_tensors
        g = grad.new_zeros(ctx.table_shape)
        g.index_add_(0, idx.reshape(-1), grad.reshape(-1, ctx.table_shape[-1]))
        return g, None


class HashGrid(nn.Module):
    """Multiresolution hash encoding of points in ``[0, 1]^3``.

    Level ``l`` has resolution ``floor(base_res * growth^l)``; levels whose dense grid fits the
    table are indexed densely, finer ones by the spatial hash of Mueller et al. Features are
    trilinearly interpolated from the 8 cell corners and concatenated over levels.
    """

    def __init__(self, num_levels: int = 12, features_per_level: int = 2, log2_table_size: int = 17,
                 base_resolution: int = 16, max_resolution: int = 512, init_scale: float = 1e-4) -> None:
        super().__init__()
        self.num_levels, self.features_per_level = num_levels, features_per_level
        self.table_size = 2**log2_table_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(num_levels - 1, 1))
        res = [int(math.floor(base_resolution * growth**level + 1e-6)) for level in range(num_levels)]
        dense = [(r + 1) ** 3 <= self.table_size for r in res]
        sizes = [(r + 1) ** 3 if d else self.table_size for r, d in zip(res, dense)]
        offsets = [0]
        for s in sizes[:-1]:
            offsets.append(offsets[-1] + s)
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("dense", torch.tensor(dense), persistent=False)
        self.num_dense = sum(dense)          # resolution grows with the level, so the dense ones come first
        assert all(dense[:self.num_dense]) and not any(dense[self.num_dense:])
        self.register_buffer("level_size", torch.tensor(sizes, dtype=torch.long), persistent=False)
        self.register_buffer("offset", torch.tensor(offsets, dtype=torch.long), persistent=False)
        self.table = nn.Parameter(torch.empty(sum(sizes), features_per_level).uniform_(-init_scale, init_scale))

    @property
    def out_dim(self) -> int:
        return self.num_levels * self.features_per_level

    @staticmethod
    def _axis_ends(lo: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Per axis the two cell ends of ``lo`` ``(N, L', 3)``, shaped to broadcast to ``(N, L', z, y, x)``."""
        n, levels = lo.shape[:2]
        ix, iy, iz = (torch.stack([lo[..., a], lo[..., a] + 1], -1) for a in range(3))   # (N, L', 2) each
        return ix.view(n, levels, 1, 1, 2), iy.view(n, levels, 1, 2, 1), iz.view(n, levels, 2, 1, 1)

    def _dense_corners(self, lo: Tensor, res: Tensor) -> Tensor:
        """``(N, L', 8)`` row-major indices of the 8 corners in the dense levels' ``(r + 1)^3`` grids."""
        ix, iy, iz = self._axis_ends(lo)
        res1 = (res.long() + 1).view(1, -1, 1, 1, 1)
        return (ix + res1 * (iy + res1 * iz)).flatten(2)

    def _hashed_corners(self, lo: Tensor) -> Tensor:
        """``(N, L', 8)`` spatial-hash indices (Mueller et al.) of the 8 corners in the hashed levels."""
        ix, iy, iz = self._axis_ends(lo)
        return ((ix * _PRIMES[0]) ^ (iy * _PRIMES[1]) ^ (iz * _PRIMES[2])).bitwise_and_(self.table_size - 1).flatten(2)

    def forward(self, x: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs E"]:
        bs = x.shape[:-1]
        if x.device.type == "cpu" and self.table.device.type == "cpu" and not x.requires_grad:
            # no gradient to the points wanted: one compiled loop (nefii.fields.hashgrid_cpu)
            out = fused_encode(self.table, x.reshape(-1, 3), self.resolution.long(), self.offset, self.num_dense,
                               self.table_size)
            return out.reshape(*bs, self.out_dim)
        x = x.reshape(-1, 3).clamp(0.0, 1.0)
        res = self.resolution.view(1, -1, 1)
        pos = x.unsqueeze(1) * res                                               # (N, L, 3)
        p0 = torch.minimum(pos.floor(), res - 1)                                 # x = 1 stays in the last cell
        frac = pos - p0
        # the 8 corners are built separably: per axis the two cell ends, broadcast to (N, L, z, y, x)
        lo = p0.long()
        nd = self.num_dense          # the coarse levels come first and are indexed densely, the rest hashed
        idx = torch.cat([self._dense_corners(lo[:, :nd], self.resolution[:nd]), self._hashed_corners(lo[:, nd:])], 1)
        idx = idx + self.offset.view(1, -1, 1)                                   # (N, L, 8), corner (z, y, x)
        f = _Gather.apply(self.table, idx)                                       # (N, L, 8, F)
        # trilinear weights in the same corner order, as products of same-shape (N, L) tensors: no
        # broadcasting, so neither backward nor the double backward of the eikonal loss has to reduce
        # over broadcast dimensions (that made this encoding twice as slow on the CPU)
        fx, fy, fz = frac.unbind(-1)
        gx, gy, gz = 1 - fx, 1 - fy, 1 - fz
        w = torch.stack([zy * xw for zy in (gz * gy, gz * fy, fz * gy, fz * fy) for xw in (gx, fx)], -1)
        # ``unbind``, not ``f[..., k]``: the backward of an index fills a zero tensor of ``f``'s size per feature
        out = torch.stack([(fk * w).sum(-1) for fk in f.unbind(-1)], -1)                               # (N, L, F)
        return out.reshape(*bs, self.out_dim)
