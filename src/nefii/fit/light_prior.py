"""A prior on the light where the object barely sees it.

The built-in scenes' images (and any capture without background pixels) constrain the environment only
through the object: a direction that the surface points' upper hemispheres rarely face, or that the object
shadows from itself, has little data gradient, and Adam, which moves a parameter by about its learning rate
whatever its gradient's size, random-walks such a lobe bright; the albedo then pays for the light it casts
(docs/experiments.md, 2026-11-26). The prior charges every part of the light its share of the energy times
how *unseen* its direction is:

    ``weight * sum_k u(d_k) E_k / sg(sum_k E_k)``

with ``E_k`` the energy of lobe (or env-map pixel) ``k`` in direction ``d_k`` and ``u = (1 - c / max c)^2``,
``c(d)`` the training points' mean ``V(x, d) max(n . d, 0)`` (the diffuse irradiance a unit light from ``d``
would give them). The best-seen directions are not pulled at all, so the prior does not trade the light the
images pin against the albedo; ``E / sg(E)`` makes it independent of the light's overall scale.

The same coverage weighs the background pixels of Eq. 7's third term and of the light solve
(:meth:`LightCoverage.seen`, ``c / max c``): the sky the camera sees pins the light where the object sees it.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from ..raycast.base import Geometry, visible_cosines
from ..render.sg import fibonacci_sphere
from .path_trace import SurfacePoints

COVERAGE_POINTS = 2048
"""training points the coverage is measured at"""
COVERAGE_DIRECTIONS = 1024
"""directions it is measured in (a spherical Fibonacci lattice: about 6.3 degrees apart)"""
UNSEEN_POWER = 2.0


@dataclass(frozen=True)
class LightCoverage:
    """How little of each direction the training points see, on a lattice of directions."""

    directions: Float[Tensor, "M 3"]
    unseen: Float[Tensor, " M"]
    """``(1 - c / max c)^2``: 0 for the best-seen direction, 1 for one no point sees"""

    def at(self, w: Float[Tensor, "K 3"]) -> Float[Tensor, " K"]:
        """``u`` at the lattice direction nearest to each unit direction ``w``."""
        return self.unseen[(w @ self.directions.T).argmax(-1)]

    def seen(self, w: Float[Tensor, "K 3"]) -> Float[Tensor, " K"]:
        """``c / max c`` at the lattice direction nearest to each unit direction ``w``: 1 for the best-seen
        direction, 0 for one no point sees."""
        return 1.0 - self.at(w).pow(1.0 / UNSEEN_POWER)


def direction_coverage(points: SurfacePoints, geometry: Geometry, directions: Float[Tensor, "M 3"],
                       ray_offset: float, chunk: int = 64) -> Float[Tensor, " M"]:
    """``c(d)``: mean over ``points`` of ``V(x, d) max(n . d, 0)``, visibility traced against ``geometry``
    (``ray_offset`` in world units) for the pairs above the surface only: the others add 0 either way."""
    cov = [visible_cosines(points.position, points.normal, points.geometric_normal, geometry, d, ray_offset).mean(0)
           for d in directions.split(chunk)]
    return torch.cat(cov)


def light_coverage(points: SurfacePoints, geometry: Geometry, ray_offset: float, seed: int = 0) -> LightCoverage:
    """The coverage of :data:`COVERAGE_DIRECTIONS` directions by :data:`COVERAGE_POINTS` of ``points`` drawn
    with ``seed`` (deterministic: a resumed fit computes the same)."""
    device = points.position.device
    g = torch.Generator(device=device).manual_seed(seed)
    pick = torch.randint(len(points.position), (COVERAGE_POINTS,), generator=g, device=device)
    directions = fibonacci_sphere(COVERAGE_DIRECTIONS, device=device)
    c = direction_coverage(points.map(lambda t: t[pick]), geometry, directions, ray_offset)
    unseen = (1.0 - c / c.max().clamp_min(1e-12)).clamp(0.0, 1.0) ** UNSEEN_POWER
    return LightCoverage(directions, unseen)


def unseen_light_prior(directions: Float[Tensor, "K 3"], energy: Float[Tensor, " K"], coverage: LightCoverage,
                       weight: float) -> Tensor:
    """``weight * sum_k u(d_k) E_k / sg(sum_k E_k)`` (the module's docstring); gradient to ``energy`` only."""
    u = coverage.at(directions.detach())
    return weight * (u * energy).sum() / energy.sum().detach().clamp_min(1e-12)
