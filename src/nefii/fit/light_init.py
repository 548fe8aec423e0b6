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

A low sun can escape that rule: a vertical face sees a direction 8 degrees above the horizon and
its mirror below at the same cosine, and the least-squares energies spread the sun over both and
their neighbours, no direction carrying a peak's share (leaning: 3.4% at most). So where the
energies hold no peak at all, the shading is also fitted by one direction plus a uniform sky
(:func:`search_sun`, 4096 directions), and that direction gets a lobe of its own. The search finds a sun to
~8 degrees only (the shading of a constant albedo says no more; where the energies do show a
peak, theirs is closer: the bowl's sun 1.8 degrees, the search's 8.7), so the lobe starts wide
(:data:`SUN_START_SHARPNESS`, ~6 degrees), which Adam moves onto the sun while the roughness warms
up (a sharp lobe that far off stays where it is), and is sharpened to a peak's sharpness when the
warm-up ends (:func:`sharpen_lobe`; a wide lobe is not sharpened by Adam). Leaning's sun left as
wide lobes cost it 1.5 dB of albedo (docs/experiments.md, 2026-11-29).

Photos without masks see the sky behind the object, and a sun in frame clips. Where the background's clipped
pixels gather in one compact patch of directions that clips in every view that sees it, dark exposures included
(:func:`sky_sun`), that patch's centre places the sun's lobe instead of the search (leaning's phone capture: 5
degrees from the sun where the shading's search is 10 off). The background pixels in that lobe's glow
(:func:`beyond_glow`, at the lobe's sharpness of the moment) are left out of Eq. 7's third term and of the light
solve, through the warm-up and after the lobe is sharpened: a 6-degree lobe standing for a 1-degree sun
over-predicts the unclipped sky around it tens of times, and those pixels pushed the lobe off the sun (leaning's
capture: 10 to 17 degrees) or the solve emptied it; sharpened 2-5 degrees off the sun, the lobe's peak lies on
unclipped sky, and the solve that followed cut its energy sevenfold (docs/experiments.md, 2026-12-02).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..raycast.base import Geometry, visible_cosines
from ..render.sg import fibonacci_sphere, sg_integral


@dataclass(frozen=True)
class LightEstimate:
    directions: Float[Tensor, "D 3"]
    """unit directions on a Fibonacci lattice"""
    energy: Float[Tensor, "D 3"]
    """``albedo / pi * L_j dOmega_j`` of each direction (non-negative, RGB)"""
    sun: Float[Tensor, "3"] | None = None
    """where no direction holds a peak: the light source the background sees (:func:`sky_sun`) if one was given,
    else the direction :func:`search_sun` found (None: a peak, no search, or no direction fits)"""


PEAK_FRACTION = 0.05
"""the share of the total energy a direction must carry to become a sharp lobe (:func:`sg_from_light`)"""

SUN_START_SHARPNESS = 100.0
"""the searched sun's lobe's sharpness until the warm-up ends (~6 degrees wide: it overlaps a sun 8 degrees
off, so the image loss moves it there)"""


def search_sun(T: Float[Tensor, "P D"], colour: Float[Tensor, "P C"]) -> tuple[int, float]:
    """The direction ``d`` (a column of ``T``, visible cosines) whose fit ``lum ~ a T_d + b s`` (``a, b >= 0``,
    ``s`` the uniform sky's shading, the mean column) leaves the least residual, and the share of the uniform
    sky's own residual it removes (0 when no direction fits with both terms non-negative)."""
    lum = colour.double().mean(-1)
    T = T.double()
    sky = T.mean(1)
    ss, sl = float(sky @ sky), float(sky @ lum)
    base = float((lum - (max(sl, 0.0) / max(ss, 1e-30)) * sky).square().sum())
    tt, ts, tl = T.square().sum(0), sky @ T, lum @ T                       # (D,) each
    det = (tt * ss - ts * ts).clamp_min(1e-30)
    a, b = (tl * ss - ts * sl) / det, (tt * sl - ts * tl) / det
    # the residual of the least-squares fit: |lum|^2 - (a tl + b sl)
    resid = float(lum @ lum) - (a * tl + b * sl)
    resid = torch.where((a >= 0) & (b >= 0) & (tt > 0), resid, torch.full_like(resid, float("inf")))
    j = int(resid.argmin())
    if not math.isfinite(float(resid[j])) or base <= 0:
        return j, 0.0
    return j, max(0.0, 1.0 - float(resid[j]) / base)


SKY_SUN_BINS = 4096
"""directions the background pixels are binned to when looking for a light source they see (~3.2 degrees apart)"""

SKY_SUN_PIXELS = 2_000_000
"""at most this many background pixels are binned (every k-th beyond it): binning costs ~25k flops a pixel, and a
100-photo capture at 512 px has ~15 M of them (the built-in captures at 128 px: 0.7 M, all binned)"""


def sky_sun(directions: Float[Tensor, "Q 3"], clipped: Bool[Tensor, " Q"], min_seen: int = 20,
            always: float = 0.99, max_spread_deg: float = 20.0) -> Float[Tensor, "3"] | None:
    """The direction of a light source the background pixels see directly, from where they clip. Their view
    directions (every k-th, at most :data:`SKY_SUN_PIXELS`) binned on a Fibonacci lattice of :data:`SKY_SUN_BINS`; a bin seen by at least ``min_seen`` pixels
    of which ``always`` or more are clipped is brighter than every view's exposure can hold (a bright sky clips
    only in the brighter views); the mean of those bins' directions, weighted by how often each is seen, when
    every one of them lies within ``max_spread_deg`` of it (one compact source); None otherwise."""
    if not bool(clipped.any()):
        return None
    stride = -(-len(directions) // SKY_SUN_PIXELS)
    directions, clipped = directions[::stride], clipped[::stride]
    lattice = fibonacci_sphere(SKY_SUN_BINS).to(directions)
    nearest = torch.cat([(part @ lattice.T).argmax(-1) for part in directions.split(4096)])   # 64 MiB at a time
    seen = torch.bincount(nearest, minlength=SKY_SUN_BINS).double()
    hot = torch.bincount(nearest[clipped], minlength=SKY_SUN_BINS).double()
    always_clipped = (seen >= min_seen) & (hot >= always * seen)
    if not bool(always_clipped.any()):
        return None
    bins = lattice[always_clipped].double()
    centre = (bins * seen[always_clipped, None]).sum(0)
    centre = centre / centre.norm()
    spread = math.degrees(math.acos(min(1.0, float((bins @ centre).min()))))
    return centre.to(directions.dtype) if spread <= max_spread_deg else None


GLOW_FLOOR = 1e-4
"""the fraction of a lobe's peak below which :func:`beyond_glow` counts a direction out of its glow"""


def beyond_glow(directions: Float[Tensor, "Q 3"], axis: Float[Tensor, "3"], sharpness: float,
                floor: float = GLOW_FLOOR) -> Bool[Tensor, " Q"]:
    """Whether each direction lies where a lobe of ``sharpness`` about the unit ``axis`` has fallen below ``floor``
    of its peak (``exp(sharpness (cos - 1)) < floor``; sharpness 100: 25 degrees, 800: 8.8)."""
    return (directions @ axis) < 1.0 - math.log(1.0 / floor) / max(sharpness, 1e-12)


@torch.no_grad()
def estimate_light(position: Tensor, normal: Tensor, geometric_normal: Tensor, colour: Tensor, geometry: Geometry,
                   num_directions: int = 1024, num_points: int = 4096, iterations: int = 200,
                   generator: torch.Generator | None = None, ray_offset: float = 1e-4,
                   sun_directions: int = 4096, peak_fraction: float = PEAK_FRACTION,
                   seen_sun: Float[Tensor, "3"] | None = None) -> LightEstimate:
    """Non-negative per-direction energies that best explain ``colour`` as diffuse shading with shadows, and,
    only where no direction carries ``peak_fraction`` of their total (no peak for :func:`sg_from_light`, the one
    case it places the sun), the sun: ``seen_sun`` (:func:`sky_sun`) if given, else the one :func:`search_sun`
    finds on ``sun_directions`` directions (0: no search)."""
    P = position.shape[0]
    idx = torch.randperm(P, generator=generator)[:num_points] if P > num_points else torch.arange(P)
    x, n, ng, c = position[idx].cpu(), normal[idx].cpu(), geometric_normal[idx].cpu(), colour[idx].cpu()
    offset = ray_offset * geometry.scale
    dirs = fibonacci_sphere(num_directions)
    T = visible_cosines(x, n, ng, geometry, dirs, offset)    # (P, D)
    e = nnls_fista(T, c, iterations)
    sun = None
    lum = e.clamp_min(0.0).mean(-1)
    no_peak = bool(lum.max() < peak_fraction * lum.sum())
    if no_peak and seen_sun is not None:
        sun = seen_sun.cpu().float()
    elif no_peak and sun_directions > 0:
        fine = fibonacci_sphere(sun_directions)
        j, explained = search_sun(visible_cosines(x, n, ng, geometry, fine, offset), c)
        sun = fine[j] if explained > 0 else None
    return LightEstimate(dirs, e, sun)


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
    sun_lobe: int | None = None
    """the lobe on the estimate's ``sun`` (seen or searched), started wide, to be sharpened when the warm-up ends
    (:func:`sharpen_lobe`)"""


def sg_from_light(est: LightEstimate, num_lobes: int, albedo: float = 0.5, num_sharp: int = 8,
                  sharp: float = 800.0, separation_deg: float = 15.0, peak_fraction: float = PEAK_FRACTION) -> SGInit:
    """Lobes for an :class:`LightEstimate`: up to ``num_sharp`` (and at most K/8) sharp lobes on directions
    that each carry at least ``peak_fraction`` of the total energy (at least ``separation_deg`` apart), or, when
    no direction does, one on the estimate's ``sun`` if it has one (with the energy around it), and wide lobes on a
    Fibonacci lattice carrying the rest; amplitudes conserve each direction's energy. The sun's lobe starts at
    :data:`SUN_START_SHARPNESS` (``SGInit.sun_lobe`` says which it is).
    (The NNLS solution is sparse, so a threshold relative to the mean would call most of a sky "peaks".)"""
    dirs, e = est.directions, est.energy.clamp_min(0.0)
    # radiant energy per direction: L_j dOmega_j = pi / albedo * e_j
    Ej = e * (math.pi / albedo)
    lum = Ej.mean(-1)
    peaks: list[int] = []
    cos_sep = math.cos(math.radians(separation_deg))
    threshold = peak_fraction * lum.sum()
    max_sharp = min(num_sharp, num_lobes // 8)
    for j in torch.argsort(lum, descending=True).tolist():
        if len(peaks) >= max_sharp or lum[j] < threshold:
            break
        if all(float(dirs[j] @ dirs[k]) < cos_sep for k in peaks):
            peaks.append(j)
    sun_axis = None                     # no peak at all: the searched sun, if any, becomes one
    if est.sun is not None and not peaks and max_sharp > 0:
        sun_axis = est.sun / est.sun.norm()
        peaks.append(int((dirs @ sun_axis).argmax()))
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
        p_axis, p_sharp = dirs[peaks].clone(), torch.full((len(peaks),), sharp)
        if sun_axis is not None:
            p_axis[-1], p_sharp[-1] = sun_axis, SUN_START_SHARPNESS
        p_mu = torch.stack(peak_energy) / sg_integral(p_sharp).unsqueeze(-1)
        axis = torch.cat([p_axis, wide_axis])
        sharpness = torch.cat([p_sharp, wide_sharp])
        amplitude = torch.cat([p_mu, wide_mu])
    else:
        axis, sharpness, amplitude = wide_axis, wide_sharp, wide_mu
    return SGInit(axis, sharpness, amplitude, len(peaks) - 1 if sun_axis is not None else None)


@torch.no_grad()
def sharpen_lobe(env, k: int, sharpness: float) -> None:
    """Lobe ``k`` of an :class:`~nefii.fields.environment.SGEnvironment` set to ``sharpness``, its amplitude scaled
    so that its integral (its energy) is unchanged."""
    old = env.log_sharpness[k].exp()
    new = torch.tensor(sharpness, dtype=old.dtype, device=old.device)
    env.log_amplitude[k] += (sg_integral(old) / sg_integral(new)).log()
    env.log_sharpness[k] = new.log()


@torch.no_grad()
def set_sg_parameters(env, init: SGInit) -> None:
    """Load ``init`` into an :class:`~nefii.fields.environment.SGEnvironment`'s parameters."""
    dev = env.axis_raw.device
    env.axis_raw.copy_(init.axis.to(dev))
    env.log_sharpness.copy_(init.sharpness.to(dev).log())
    env.log_amplitude.copy_(init.amplitude.to(dev).clamp_min(1e-4).log())
