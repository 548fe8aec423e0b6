"""The hash grid's encoding and its table gradient as one compiled CPU loop (numba), run either way.

:class:`~nefii.fields.encodings.HashGrid` in PyTorch builds every level's 8 corner indices, gathers the
corners, multiplies by the trilinear weights and sums: a dozen tensor operations of ``N x L x 8`` elements,
each a pass over memory, and as many again in the backward. Here one loop (:func:`_sweep`) does a point's
levels in registers: forward it reads the table and writes ``(N, L, F)``; backward it recomputes the corners
and adds ``w * grad`` into the table's gradient. Same indexing and weights as the PyTorch path (dense levels
row-major over ``(r + 1)^3`` corners, hashed levels by Mueller et al.'s primes); only the order of the
floating-point sums differs.

What it does not do: a gradient with respect to the points (the geometry stage's SDF and the refinement
need it, and its double backward for the eikonal term); :class:`HashGrid` keeps the PyTorch path there.
One thread: the loops are memory-bound and short (a fit's batch), and a thread pool would wait on the
other process when the CPU is shared (issue 28's contention figures). numba compiles the loop on first use
(~2.5 s) and caches it beside this module.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

_P1, _P2 = 2654435761, 805459861


@numba.njit(cache=True, nogil=True)
def _corners(x: np.ndarray, n: int, r: int, dense: bool, size_mask: int, idx: np.ndarray, w: np.ndarray) -> None:
    """The 8 corner rows (within the level) and trilinear weights of point ``x[n]``, clamped to ``[0, 1]^3``, at
    resolution ``r``, in the PyTorch path's corner order ``(z, y, x)``."""
    rf = float(r)
    fx = min(max(x[n, 0], 0.0), 1.0) * rf
    fy = min(max(x[n, 1], 0.0), 1.0) * rf
    fz = min(max(x[n, 2], 0.0), 1.0) * rf
    x0, y0, z0 = min(np.floor(fx), rf - 1.0), min(np.floor(fy), rf - 1.0), min(np.floor(fz), rf - 1.0)
    tx, ty, tz = fx - x0, fy - y0, fz - z0
    ix, iy, iz = int(x0), int(y0), int(z0)
    k = 0
    for dz in range(2):
        wz = tz if dz else 1.0 - tz
        for dy in range(2):
            wzy = wz * (ty if dy else 1.0 - ty)
            for dx in range(2):
                w[k] = wzy * (tx if dx else 1.0 - tx)
                cx, cy, cz = ix + dx, iy + dy, iz + dz
                if dense:
                    idx[k] = cx + (r + 1) * (cy + (r + 1) * cz)
                else:
                    idx[k] = (cx ^ (cy * _P1) ^ (cz * _P2)) & size_mask
                k += 1


@numba.njit(cache=True, nogil=True)
def _sweep(x: np.ndarray, table: np.ndarray, res: np.ndarray, offset: np.ndarray, num_dense: int, size_mask: int,
           features: np.ndarray, backward: bool) -> None:
    """Every point ``x (N, 3)`` at every level: the forward (``backward`` False) writes
    ``features[n, l, f] = sum_c w_c table[offset_l + idx_c, f]``; the backward adds
    ``w_c features[n, l, f]`` (the features' gradient) into ``table`` (the table's gradient, zeroed by the caller)."""
    idx, w = np.empty(8, np.int64), np.empty(8, x.dtype)
    for n in range(x.shape[0]):
        for level in range(res.shape[0]):
            _corners(x, n, res[level], level < num_dense, size_mask, idx, w)
            base = offset[level]
            for f in range(table.shape[1]):
                if backward:
                    g = features[n, level, f]
                    for c in range(8):
                        table[base + idx[c], f] += w[c] * g
                else:
                    acc = 0.0
                    for c in range(8):
                        acc += w[c] * table[base + idx[c], f]
                    features[n, level, f] = acc


class FusedHashEncode(torch.autograd.Function):
    """``(table (T, F), x (N, 3)) -> (N, L, F)`` on the CPU; the gradient reaches the table only."""

    @staticmethod
    def forward(ctx, table: Tensor, x: Tensor, res: Tensor, offset: Tensor, num_dense: int, table_size: int) -> Tensor:
        x = x.detach().to(table.dtype).contiguous()
        t = table.detach().contiguous()
        out = torch.empty(len(x), len(res), t.shape[1], dtype=t.dtype)
        _sweep(x.numpy(), t.numpy(), res.numpy(), offset.numpy(), num_dense, table_size - 1, out.numpy(), False)
        ctx.save_for_backward(x, res, offset)
        ctx.num_dense, ctx.table_size, ctx.table_shape = num_dense, table_size, t.shape
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, res, offset = ctx.saved_tensors
        grad_table = torch.zeros(ctx.table_shape, dtype=grad.dtype)
        _sweep(x.numpy(), grad_table.numpy(), res.numpy(), offset.numpy(), ctx.num_dense, ctx.table_size - 1,
               grad.contiguous().numpy(), True)
        return grad_table, None, None, None, None, None


def fused_encode(table: Tensor, x: Tensor, resolution: Tensor, offset: Tensor, num_dense: int,
                 table_size: int) -> Tensor:
    """The hash grid's ``(N, L, F)`` features of points ``x (N, 3)`` in ``[0, 1]^3`` (clamped), CPU tensors;
    ``resolution (L,)`` and ``offset (L,)`` int64, the first ``num_dense`` levels dense."""
    return FusedHashEncode.apply(table, x, resolution, offset, num_dense, table_size)
