"""The fit's unit of radiance: colours whose brightest object pixels lie outside the range the fit was made for
are divided by one number taken from them, so that a fit does not break on a dark or a bright exposure.

The losses compare colours through ``log1p`` (linear below ~1, logarithmic above), the priors' weights are set
against the losses' size, and the light solve's floor and the cache's ``softplus`` are absolute: all of them
read the same scene photographed darker, or stored in other HDR units, as another problem. On 2026-11-30 the
corner's images times 8 fitted to roughness MSE 0.0288 and times 1/8 to 0.0607 and 6.6 dB less albedo, against
0.0163 as rendered (docs/experiments.md). Inside the range (:data:`LOW` to :data:`HIGH` for the 99th percentile
of the object pixels' luminance: the built-in scenes' renders and photos read 0.52-1.2) the colours are left as
they are; outside it they are scaled to its nearer end. The written model is put back into the images' units
(:func:`rescale_radiance`), so eval, relight and export read it as before.
"""
from __future__ import annotations

from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor

from ..errors import InputError
from .model import NeFIIModel

QUANTILE = 0.99
"""the quantile of the object pixels' luminance (the mean of R, G, B) that sets the unit"""
LOW, HIGH = 0.5, 1.25
"""the range of that quantile the fit takes colours in as they are"""
SAMPLE = 1 << 20
"""at most this many pixels (every k-th) are read for the quantile"""


def radiance_unit(rgb: Float[Tensor, "P 3"], where: Path | None = None) -> float:
    """The images' radiance that the fit calls 1: 1 where the :data:`QUANTILE` of the object pixels' luminance
    lies in [:data:`LOW`, :data:`HIGH`], else the quantile over the nearer end, so that two exposures beyond the
    same end give one fit (exactly when they differ by a power of 2). :class:`InputError` (naming ``where``) if
    the object's pixels are all black."""
    lum = rgb[:: -(-len(rgb) // SAMPLE)].float().mean(-1)
    top = float(torch.quantile(lum, QUANTILE)) if len(lum) else 0.0
    if not top > 0.0:
        raise InputError(where, "99% of the object's pixels are black: is the exposure or the mask wrong?")
    return top / min(max(top, LOW), HIGH)


@torch.no_grad()
def rescale_radiance(model: NeFIIModel, k: float) -> None:
    """Everything ``model`` says in units of radiance times ``k``, in place: the environment and the radiance
    cache. The material is a ratio and does not change."""
    model.env.scale_radiance(k)
    model.cache.radiance_unit.mul_(k)
