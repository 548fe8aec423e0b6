"""Per-view exposure and white balance: a learned RGB gain per training view (``exposure = per_view``).

A photo's colour is ``g_v * L``: the scene's radiance ``L`` times the camera's gain for that view (exposure
time, ISO, white balance). The fit multiplies what it renders for view ``v`` by ``g_v`` before comparing
with the pixels, so a view shot one stop brighter than the others is explained by a gain twice theirs, not
by a brighter sky or albedo. The gains' geometric mean is held at 1 per channel (``log g`` centred over the
views): without that every gain could double while the light halves. Centring, not fixing one reference
view, keeps that scale out of the gains altogether: with a reference, the other views' gains share one
direction that only the reference's pixels constrain, and the fit crawls along it (measured: one view of
twelve left the other eleven 13% off after 600 steps). A small prior pulls each ``log g_v`` to where it
starts: 0, or, when every photo has an EXIF exposure ``e_v`` (``t * ISO / N^2``), ``log e_v`` centred over
the views (the camera's own record of its exposure; white balance is left to the fit). The
materials, the light and the cache are those of the views' average exposure; eval and relight render
without gains.
"""
from __future__ import annotations

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

GAIN_PRIOR = 1e-3
"""weight of ``mean((log g - log g_0)^2)``: a tie-breaker where the images say nothing about a gain (a view
whose pixels are all clipped), far below the colour loss of any view with data"""


def metered_log_gains(metered: Float[Tensor, "V"]) -> Float[Tensor, "V"]:
    """``log e_v`` centred over the views: where the gains of views with EXIF exposures ``metered`` start."""
    log_e = metered.double().log()
    return (log_e - log_e.mean()).float()


def without_gains(rgb: Float[Tensor, "P 3"], view: Int[Tensor, "P"],
                  log_gain: Float[Tensor, "V"]) -> Float[Tensor, "P 3"]:
    """Pixel colours ``rgb`` from views ``view`` divided by their views' gains ``exp(log_gain)``: the radiance
    the model renders for them."""
    return rgb / log_gain.to(rgb).exp()[view][:, None]


class ViewGains(nn.Module):
    """A free ``log g`` per view and channel, centred over the views; starts at gain 1 everywhere, or at the
    views' ``metered`` exposures (EXIF) relative to their geometric mean."""

    def __init__(self, num_views: int, metered: Float[Tensor, "V"] | None = None) -> None:
        super().__init__()
        if num_views < 1:
            raise ValueError(f"ViewGains needs at least one view, got {num_views}")
        start = torch.zeros(num_views, 3)
        if metered is not None:
            if metered.shape != (num_views,) or not bool((metered > 0).all()):
                raise ValueError(f"metered exposures must be ({num_views},) and positive, got {tuple(metered.shape)}")
            start = metered_log_gains(metered)[:, None].expand(num_views, 3).clone()
        self.register_buffer("expected", start.clone(), persistent=False)   # from the data, not the fit
        self.log_gain = nn.Parameter(start)

    @property
    def num_views(self) -> int:
        return self.log_gain.shape[0]

    def centred(self) -> Float[Tensor, "V 3"]:
        """``log g`` with its mean over the views removed (one view: 0)."""
        return self.log_gain - self.log_gain.mean(0, keepdim=True)

    def all(self) -> Float[Tensor, "V 3"]:
        """Every view's gain; their geometric mean is 1 in each channel."""
        return self.centred().exp()

    def forward(self, view: Int[Tensor, "B"]) -> Float[Tensor, "B 3"]:
        """The gains of the views ``view`` (indices into the training views)."""
        return self.all()[view]

    def prior(self) -> Tensor:
        """``GAIN_PRIOR * mean((log g - log g_0)^2)`` over the views' centred gains, ``g_0`` where they started."""
        return GAIN_PRIOR * (self.centred() - self.expected).square().mean()
