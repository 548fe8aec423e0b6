"""Initial lighting from shading and shadows on the known geometry.

Before the joint optimisation, find where the light comes from: with the geometry frozen, the
irradiance of a diffuse point is ``sum_j L_j dOmega_j V(x, w_j) max(0, n . w_j)`` over
directions ``w_j``. Assuming a constant albedo, the observed colours ``c_i`` of the object
pixels give a non-negative least-squares problem for the per-direction energies

    min_{e >= 0} || T e - c ||^2,   T_ij = V(x_i, w_j) max(0, n_i . w_j)

solved by projected gradient descent (FISTA). Shadows make a hard sun stand out as one bright
direction: sun shading and shadows are then explained by light from the first step instead of
being painted into the albedo (learning light only by gradient descent does not: a minimal fit
whose 128 lobes started at sharpness 10 on a Fibonacci sphere did not localise a 1-degree sun of
radiance 2500 after 10 minutes; the strongest lobes stayed at sharpness ~9 near the zenith, and
the sun's shading and shadows went into the albedo). The solution initialises the SG
lobes: the brightest, well-separated directions become sharp lobes, the rest a smooth sky of
wide lobes on a Fibonacci lattice.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from ..raycast.base import Geometry, visible_cosines
from ..render.sg import fibonacci_sphere, sg_integral


@dataclass(frozen=True)
class LightEstimate:
    directions: Float[Tensor, "D 3"]
    """unit directions on a Fibonacci lattice"""
    energy: Float[Tensor, "D 3"]
    """``albedo / pi * L_j dOmega_j`` of each direction (non-negative, RGB)"""


@torch.no_grad()
def estimate_light(position: Tensor, normal: Tensor, geometric_normal: Tensor, colour: Tensor, geometry: Geometry,
                   num_directions: int = 1024, num_points: int = 4096, iterations: int = 200,
                   generator: torch.Generator | None = None, ray_offset: float = 1e-4) -> LightEstimate:
    """Non-negative per-direction energies that best explain ``colour`` as diffuse shading with shadows."""
    P = position.shape[0]
    idx = torch.randperm(P, generator=generator)[:num_points] if P > num_points else torch.arange(P)
    x, n, ng, c = position[idx].cpu(), normal[idx].cpu(), geometric_normal[idx].cpu(), colour[idx].cpu()
    dirs = fibonacci_sphere(num_directions)
    T = visible_cosines(x, n, ng, geometry, dirs, ray_offset * geometry.scale)    # (P, D)
    e = nnls_fista(T, c, iterations)
    return LightEstimate(dirs, e)


def nnls_fista(A: Float[Tensor, "P D"], b: Float[Tensor, "P C"], iterations: int) -> Float[Tensor, "D C"]:
    """``argmin_{x >= 0} ||A x - b||^2`` per column of ``b`` by accelerated projected gradient."""
    # Lipschitz constant of the gradient: the largest eigenvalue of A^T A (power iteration)
    v = torch.ones(A.shape[1], 1, dtype=A.dtype)
    for _ in range(30):
        v = A.T @ (A @ v)
        lip = v.norm()
        v = v / lip.clamp_min(1e-30)
    step = 1.0 / lip.clamp_min(1e-30)
    x = torch.zeros(A.shape[1], b.shape[1], dtype=A.dtype)
    y, t = x.clone(), 1.0
    Atb = A.T @ b
    for _ in range(iterations):
        x_new = (y - step * (A.T @ (A @ y) - Atb)).clamp_min(0.0)
        t_new = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * t * t))
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        x, t = x_new, t_new
    return x


@dataclass(frozen=True)
class SGInit:
    axis: Float[Tensor, "K 3"]
    sharpness: Float[Tensor, " K"]
    amplitude: Float[Tensor, "K 3"]


def sg_from_light(est: LightEstimate, num_lobes: int, albedo: float = 0.5, num_sharp: int = 8,
                  sharp: float = 800.0, separation_deg: float = 15.0, peak_fraction: float = 0.05) -> SGInit:
    """Lobes for an :class:`LightEstimate`: up to ``num_sharp`` (and at most K/8) sharp lobes on directions
    that each carry at least ``peak_fraction`` of the total energy (at least ``separation_deg`` apart), and
    wide lobes on a Fibonacci lattice carrying the rest; amplitudes conserve each direction's energy.
    (The NNLS solution is sparse, so a threshold relative to the mean would call most of a sky "peaks".)"""
    dirs, e = est.directions, est.energy.clamp_min(0.0)
    # radiant energy per direction: L_j dOmega_j = pi / albedo * e_j
    Ej = e * (math.pi / albedo)
    lum = Ej.mean(-1)
    peaks: list[int] = []
    cos_sep = math.cos(math.radians(separation_deg))
    threshold = peak_fraction * lum.sum()
    for j in torch.argsort(lum, descending=True).tolist():
        if len(peaks) >= min(num_sharp, num_lobes // 8) or lum[j] < threshold:
            break
        if all(float(dirs[j] @ dirs[k]) < cos_sep for k in peaks):
            peaks.append(j)
    K_wide = num_lobes - len(peaks)
    wide_axis = fibonacci_sphere(K_wide)
    spacing = math.sqrt(4 * math.pi / K_wide)
    wide_sharp = torch.full((K_wide,), 1.0 / spacing**2)
    # the peaks' own energy goes to their sharp lobes; everything else to the nearest wide lobe
    rest = Ej.clone()
    peak_energy = []
    for j in peaks:
        # the peak and the bright directions right around it (a sun leaks into its lattice neighbours)
        part = ((dirs @ dirs[j]) > math.cos(math.radians(0.75 * separation_deg))) & (lum > 0.05 * lum[j])
        peak_energy.append(Ej[part].sum(0))
        rest[part] = 0.0
    owner = (dirs @ wide_axis.T).argmax(-1)                                   # (D,)
    wide_E = torch.zeros(K_wide, 3).index_add_(0, owner, rest)
    wide_mu = wide_E / sg_integral(wide_sharp).unsqueeze(-1)
    if peaks:
        p_axis = dirs[peaks]
        p_sharp = torch.full((len(peaks),), sharp)
        p_mu = torch.stack(peak_energy) / sg_integral(p_sharp).unsqueeze(-1)
        axis = torch.cat([p_axis, wide_axis])
        sharpness = torch.cat([p_sharp, wide_sharp])
        amplitude = torch.cat([p_mu, wide_mu])
    else:
        axis, sharpness, amplitude = wide_axis, wide_sharp, wide_mu
    return SGInit(axis, sharpness, amplitude)


@torch.no_grad()
def set_sg_parameters(env, init: SGInit) -> None:
    """Load ``init`` into an :class:`~nefii.fields.environment.SGEnvironment`'s parameters."""
    dev = env.axis_raw.device
    env.axis_raw.copy_(init.axis.to(dev))
    env.log_sharpness.copy_(init.sharpness.to(dev).log())
    env.log_amplitude.copy_(init.amplitude.to(dev).clamp_min(1e-4).log())
