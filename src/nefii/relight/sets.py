"""What one ``nefii relight`` output folder holds: the views, the light of each, and the truth to score against.

Two sources: a map file given on the command line (every view under it; scored where the dataset has the
same views relit under a map of that name), or the dataset's own relit views (:func:`dataset_sets`), each
set under its own map or, for other photographs at their own poses (Stanford-ORB), each view under its own.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..data.scene import Relit, SceneData
from ..errors import InputError
from ..render.envmap import Environment
from .cameras import Views
from .environment import environment_from_radiance


@dataclass(frozen=True)
class RelightSet:
    """One folder of relit views."""

    name: str
    """the output folder under ``OUT`` and the key in ``metrics.json``"""
    views: Views
    """the cameras to render and the names of the outputs"""
    light: Callable[[int], Environment]
    """the environment of view ``v``"""
    envmap: str
    """what lit it, in words, for ``render.json`` and ``metrics.json``"""
    radiance: Float[Tensor, "*N He We 3"]
    """the map behind ``light``: one for the set, or one per view (``N`` first); what a render's key hashes
    without building every view's sampling tables"""
    truth: Float[Tensor, "N H W 3"] | None = None
    """linear straight colour to score each view against; ``None``: not scored"""
    masks: Bool[Tensor, "N H W"] | None = None
    """the pixels scored; ``None``: where the render covers the pixel more than half"""


def scoring_masks(scene: SceneData) -> Bool[Tensor, "N H W"] | None:
    """The object pixels of the split's views: the ground-truth mask, else the views' masks."""
    gt = scene.ground_truth
    return gt.mask if gt is not None and gt.mask is not None else scene.masks


def relit_indices(relit: Relit, scene: SceneData) -> tuple[int, ...]:
    """Output names of the relit views: their own indices, else the split's."""
    return scene.indices if relit.indices is None else relit.indices


def _light_of(relit: Relit, scene: SceneData, device: torch.device) -> Callable[[int], Environment]:
    """The light of each view of ``relit``: one :class:`Environment` for the set, or one per view built when
    that view is rendered (its sampling tables are as large as its map)."""
    if relit.view_envmaps is not None:
        def own(v: int) -> Environment:
            return environment_from_radiance(relit.view_envmaps[v], f"{scene.root}: relit '{relit.name}' view "
                                             f"{relit_indices(relit, scene)[v]}: its environment map", device=device)
        return own
    if relit.envmap is None:
        raise InputError(scene.root, f"relit views '{relit.name}' have no environment map to render them under "
                                     f"(nefii layout: relight/{relit.name}.exr)")
    shared = environment_from_radiance(relit.envmap, f"{scene.root}: relit '{relit.name}': its environment map",
                                       device=device)
    return lambda v: shared


def dataset_sets(scene: SceneData, device: torch.device) -> list[RelightSet]:
    """Every relit set of the (test) split, each view under the dataset's own map, scored against its images."""
    if not scene.relit:
        raise InputError(scene.root, f"the {scene.split} split ({scene.format}) has no relit views to render: "
                                     "nefii layout relight/<env>/ with relight/<env>.exr, Stanford-ORB "
                                     "transforms_novel.json")
    out = []
    for r in scene.relit:
        own = r.cameras is not None
        views = Views(r.cameras if own else scene.cameras, relit_indices(r, scene))
        what = ("each view's own map, from the dataset, in the world frame" if r.view_envmaps is not None
                else f"the dataset's map of '{r.name}'")
        radiance = r.view_envmaps if r.view_envmaps is not None else r.envmap
        out.append(RelightSet(r.name, views, _light_of(r, scene, device), what, radiance, r.images,
                              r.masks if own else scoring_masks(scene)))
    return out
