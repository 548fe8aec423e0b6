"""Chi-square goodness-of-fit test of a direction sampler against its own pdf.

In the manner of Mitsuba 3's ``ChiSquareTest`` (``mitsuba/python/chi2.py``): draw many
directions, histogram them, integrate the pdf over every bin by quadrature to get the expected
counts, pool the cells expected fewer than 5 times, and ask ``scipy.stats.chi2.sf`` how likely
a statistic at least this large is if the samples follow the pdf.

The bins live in a frame centred on a direction ``c`` the distribution is concentrated about
(the normal, a mirror direction, a lobe axis), so that sharp lobes are spread over many bins:
with ``t = 1 - cos(theta')`` the polar coordinate is warped to

    x = (1 - exp(-kappa t)) / (1 - exp(-2 kappa))   in [0, 1]   (x = t / 2 for kappa = 0)

and ``x`` and ``phi'`` are cut into equal bins. The bins cover the whole sphere. ``kappa`` is
chosen from the width of the lobe, never equal to the inverse CDF of the sampler under test.
Expected counts come from :mod:`quadrature` (graded Gauss-Legendre in float64).

Many chi-square tests in one suite would fail now and then by chance; :func:`sidak_level` gives
the per-test significance that keeps the chance of any false failure at ``alpha`` (Mitsuba's
``significance_level = 1 - (1 - alpha)^(1 / test_count)``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.stats
import torch
from torch import Tensor

from quadrature import DTYPE, centred_coordinates, centred_direction, graded_rule, orthonormal_frame, uniform_rule

Sampler = Callable[[Tensor], Tensor]
"""``(N, dim_u)`` uniform numbers -> ``(N, 3)`` directions."""
Pdf = Callable[[Tensor], Tensor]
"""``(..., 3)`` unit directions -> ``(...)`` density over solid angle."""

POOL_THRESHOLD = 5.0
LEVEL_FOR_POWER = 1e-6
"""p-value a deliberately wrong pdf must fall below, to show the test can fail."""


def sidak_level(alpha: float, test_count: int) -> float:
    """Per-test significance so that ``test_count`` independent tests all pass with probability ``1 - alpha``."""
    return 1.0 - (1.0 - alpha) ** (1.0 / test_count)


@dataclass(frozen=True)
class SphericalBinning:
    """Bins over the whole sphere in a frame centred on ``centre``, polar axis warped by ``kappa``."""

    centre: tuple[float, float, float]
    """the direction the bins are centred on (need not be unit)"""
    kappa: float
    """zoom of the polar warp: about 1 / (the lobe's width in t = 1 - cos); 0 for uniform in cos"""
    n_theta: int = 32
    """bins along the warped polar coordinate x"""
    n_phi: int = 32
    """bins along the azimuth phi' about the centre"""

    @property
    def frame(self) -> tuple[Tensor, Tensor, Tensor]:
        return orthonormal_frame(self.centre)

    def warp(self, t: Tensor) -> Tensor:
        """``t = 1 - cos(theta')`` in [0, 2] -> ``x`` in [0, 1]."""
        if self.kappa == 0.0:
            return t / 2.0
        return torch.expm1(-self.kappa * t) / math.expm1(-2.0 * self.kappa)

    def unwarp(self, x: Tensor) -> Tensor:
        """Inverse of :meth:`warp`."""
        if self.kappa == 0.0:
            return 2.0 * x
        return (-torch.log1p(x * math.expm1(-2.0 * self.kappa)) / self.kappa).clamp(0.0, 2.0)

    def t_edges(self) -> Tensor:
        edges = self.unwarp(torch.linspace(0.0, 1.0, self.n_theta + 1, dtype=DTYPE))
        edges[0], edges[-1] = 0.0, 2.0
        return edges

    def bin_of(self, w: Tensor) -> Tensor:
        """Flat bin index ``i_theta * n_phi + i_phi`` of each direction in ``w`` (N, 3)."""
        t, phi = centred_coordinates(self.frame, w.to(DTYPE))
        i = (self.warp(t) * self.n_theta).long().clamp(0, self.n_theta - 1)
        j = (phi * (self.n_phi / (2.0 * math.pi))).long().clamp(0, self.n_phi - 1)
        return i * self.n_phi + j

    def integrate(self, pdf: Pdf, *, order: int = 4, phi_panels: int = 16, ds_max: float = 0.5,
                  dt_max: float = 0.01) -> Tensor:
        """``int_bin pdf`` for every bin, shape (n_theta, n_phi): graded Gauss-Legendre in t, uniform in phi'."""
        frame = self.frame
        phi, w_phi = uniform_rule(0.0, 2.0 * math.pi, self.n_phi * phi_panels, order)
        edges = self.t_edges()
        # grading towards the centre on the scale of the first bin
        eps = 1e-3 * float(edges[1])
        out = torch.empty(self.n_theta, self.n_phi, dtype=DTYPE)
        for i in range(self.n_theta):
            t, w_t = graded_rule(float(edges[i]), float(edges[i + 1]), eps, order, ds_max, dt_max)
            values = pdf(centred_direction(frame, t.unsqueeze(-1), phi))          # (M, P)
            per_phi = (w_t.unsqueeze(-1) * values).sum(0) * w_phi                 # (P,)
            out[i] = per_phi.reshape(self.n_phi, -1).sum(-1)
        return out


def pooled_chi2(observed: np.ndarray, expected: np.ndarray,
                pool_threshold: float = POOL_THRESHOLD) -> tuple[float, int, str | None]:
    """Chi-square statistic and degrees of freedom, pooling low cells as Mitsuba's ``math::chi2`` does.

    Cells are visited by increasing expected count; those expected fewer than
    ``pool_threshold`` times are merged until the merged cell reaches the threshold.
    Returns ``(statistic, dof, failure)``; ``failure`` is a message (and the statistic inf)
    when a cell the pdf gives no mass to received samples.
    """
    observed = np.asarray(observed, dtype=np.float64).ravel()
    expected = np.asarray(expected, dtype=np.float64).ravel()
    impossible = (expected <= 0.0) & (observed > 0)
    if impossible.any():
        return math.inf, 0, (f"{int(observed[impossible].sum())} samples fell in {int(impossible.sum())} "
                             "cells where the pdf integrates to 0")
    order = np.argsort(expected, kind="stable")
    stat, dof, pool_obs, pool_exp = 0.0, 0, 0.0, 0.0
    for k in order:
        o, e = observed[k], expected[k]
        if e <= 0.0:
            continue
        if e < pool_threshold:
            pool_obs, pool_exp = pool_obs + o, pool_exp + e
            if pool_exp >= pool_threshold:
                stat += (pool_obs - pool_exp) ** 2 / pool_exp
                dof += 1
                pool_obs, pool_exp = 0.0, 0.0
        else:
            stat += (o - e) ** 2 / e
            dof += 1
    if pool_exp > 0.0:
        stat += (pool_obs - pool_exp) ** 2 / pool_exp
        dof += 1
    return stat, dof - 1, None


@dataclass(frozen=True)
class ChiSquareResult:
    """Outcome of :func:`chi2_test`."""

    statistic: float
    dof: int
    p_value: float
    pdf_integral: float
    """quadrature of the pdf over all bins, i.e. over the whole sphere"""
    observed: np.ndarray
    """(n_theta, n_phi) sample counts"""
    expected: np.ndarray
    """(n_theta, n_phi) num_samples * integral of the pdf over each bin"""
    failure: str | None = None

    def describe(self) -> str:
        worst = np.unravel_index(np.argmax((self.observed - self.expected) ** 2 / np.maximum(self.expected, 1e-12)),
                                 self.expected.shape)
        return (f"chi2 = {self.statistic:.1f} on {self.dof} dof, p = {self.p_value:.3g}, "
                f"int pdf = {self.pdf_integral:.6f}, worst bin {tuple(int(i) for i in worst)}: "
                f"observed {self.observed[worst]:.0f} expected {self.expected[worst]:.1f}"
                + (f"; {self.failure}" if self.failure else ""))


def draw_uniform(num_samples: int, dim: int, seed: int) -> Tensor:
    """``(num_samples, dim)`` uniform float64 numbers from a seeded generator."""
    gen = torch.Generator().manual_seed(seed)
    return torch.rand((num_samples, dim), generator=gen, dtype=DTYPE)


def histogram(samples: Tensor, binning: SphericalBinning) -> np.ndarray:
    """(n_theta, n_phi) counts of the directions ``samples`` (N, 3)."""
    counts = torch.bincount(binning.bin_of(samples), minlength=binning.n_theta * binning.n_phi)
    return counts.reshape(binning.n_theta, binning.n_phi).numpy().astype(np.float64)


def chi2_test(sample: Sampler | None, pdf: Pdf | None, binning: SphericalBinning, *, dim_u: int = 2,
              seed: int = 0, num_samples: int = 1_000_000, samples: Tensor | None = None,
              integral: Tensor | None = None) -> ChiSquareResult:
    """Histogram ``sample(u)`` for seeded uniform ``u`` and test it against ``pdf`` integrated over the bins.

    ``samples`` may be given instead of ``sample`` (directions already drawn), and ``integral``
    (``binning.integrate(pdf)``, e.g. cached across seeds) instead of ``pdf``.
    Samples that are not finite unit vectors fail the test.
    """
    if samples is None:
        samples = sample(draw_uniform(num_samples, dim_u, seed))
    if integral is None:
        integral = binning.integrate(pdf)
    samples = samples.to(DTYPE)
    num_samples = samples.shape[0]
    valid = torch.isfinite(samples).all(-1) & ((samples.norm(dim=-1) - 1.0).abs() < 1e-6)
    observed = histogram(samples[valid], binning)
    integral = integral.numpy()
    expected = num_samples * integral
    if not bool(valid.all()):
        stat, dof, failure = math.inf, 0, f"{int((~valid).sum())} samples are not finite unit vectors"
    else:
        stat, dof, failure = pooled_chi2(observed, expected)
    p = 0.0 if failure is not None else float(scipy.stats.chi2.sf(stat, dof))
    return ChiSquareResult(statistic=stat, dof=dof, p_value=p, pdf_integral=float(integral.sum()),
                           observed=observed, expected=expected, failure=failure)
