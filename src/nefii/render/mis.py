"""Multiple importance sampling weights (Veach 1997), power heuristic with beta = 2.

With one sample from each of S strategies, the estimator of ``int g`` is
``sum_s w_s(x_s) g(x_s) / p_s(x_s)`` with ``w_s = p_s^2 / sum_j p_j^2``.
Both helpers scale by the largest density first so squares neither overflow nor
underflow, and return 0 where the weight is not finite (0/0, inf/inf).
"""
from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def power_heuristic(p_s: Float[Tensor, "*bs"], p_all: Float[Tensor, "*bs S"]) -> Float[Tensor, "*bs"]:
    """``p_s^2 / sum_j p_j^2``; ``p_all`` holds the densities of all strategies (including s)."""
    m = p_all.amax(-1)
    w = (p_s / m) ** 2 / ((p_all / m.unsqueeze(-1)) ** 2).sum(-1)
    return torch.where(torch.isfinite(w), w, torch.zeros_like(w))


def power_heuristic_over_pdf(p_s: Float[Tensor, "*bs"], p_all: Float[Tensor, "*bs S"]) -> Float[Tensor, "*bs"]:
    """``w_s / p_s = p_s / sum_j p_j^2``: the factor a sample's integrand is multiplied by."""
    m = p_all.amax(-1)
    w = (p_s / m) / ((p_all / m.unsqueeze(-1)) ** 2).sum(-1) / m
    return torch.where(torch.isfinite(w) & (p_s > 0), w, torch.zeros_like(w))
