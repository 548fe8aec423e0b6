"""Configuration of the geometry stage: one dataclass, a docstring per field, presets in one place."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from ..config_tools import Range, apply_overrides, check_memory, dataclass_from_dict, nearest, validate
from ..fit.config import NetworkConfig, network_numbers


@dataclass
class GeometryConfig:
    preset: Literal["cpu", "gpu", "paper", "tiny"] = "cpu"
    """the preset these values started from"""
    steps: Annotated[int, Range(1)] = 18000
    """optimisation steps (``cpu``: 18000, about 23 minutes for 64 views at 128 px on one core; the fits on the
    reconstructions 0.3 dB better in albedo on the mean of four scenes and two seeds than at 12000, roughness
    better on each; docs/experiments.md, 2026-11-30)"""
    batch_rays: Annotated[int, Range(1)] = 512
    """rays per step"""
    foreground_rays: Annotated[float, Range(0, 1)] = 0.5
    """with masks, this fraction of each batch is drawn from the pixels inside the masks and the rest
    from all pixels: more rays where the colour loss has something to say (the mask loss is
    reweighted so that it stays the mean over all pixels)"""
    samples: Annotated[int, Range(2, 4096)] = 32
    """stratified samples per ray inside the unit sphere"""
    importance: Annotated[int, Range(0, 4096)] = 32
    """extra samples per ray by NeuS's hierarchical up-sampling (in ``importance_rounds`` rounds)"""
    importance_rounds: Annotated[int, Range(0, 16)] = 2
    """rounds of up-sampling, at fixed sharpness 64 * 2^i"""
    background_samples: Annotated[int, Range(1, 4096)] = 16
    """samples per ray of the NeRF++ background (used without masks)"""
    lr: Annotated[float, Range(0, 10, lo_open=True)] = 1e-2
    """Adam learning rate of the SDF's encoding (a hash-grid table wants a large step)"""
    lr_networks: Annotated[float, Range(0, 10, lo_open=True)] = 2e-3
    """Adam learning rate of the MLPs, the sharpness and the background"""
    lr_decay: Annotated[float, Range(0, 1, lo_open=True)] = 0.1
    """learning rates fall exponentially to this fraction at the last step"""
    eikonal_weight: Annotated[float, Range(0)] = 0.1
    """weight of the eikonal loss ``(|grad f| - 1)^2`` (NeuS: 0.1)"""
    area_weight: Annotated[float, Range(0)] = 0.1
    """weight of a minimal-surface prior, the mean of ``exp(-area_sharpness |f(u)|)`` over
    ``area_points`` random points in the ball (proportional to the area of the zero level set, as
    SparseNeuS's sparseness loss): where no view constrains the surface (the underside of an object
    standing on something, seen only from above) it spans the observed edges by the smallest
    surface instead of keeping the initial sphere. Too strong, it lids hollows the views look into
    (the bowl at 0.3; see src/nefii/sdf/design.md)"""
    area_sharpness: Annotated[float, Range(0, lo_open=True)] = 50.0
    """``tau`` of the minimal-surface prior, in 1 / normalised units"""
    area_points: Annotated[int, Range(1)] = 2048
    """random points per step of the minimal-surface prior"""
    normal_smoothness: Annotated[float, Range(0)] = 0.0
    """weight of a prior that the surface normal varies slowly along the surface: ``|n(x) - n(x + t)|``
    at the rendered surface points ``x`` with ``t`` a random step in the tangent plane of std
    ``normal_radius`` (a hash grid's gradient is local to its cells and turns bumpy without it)"""
    normal_radius: Annotated[float, Range(0, 1)] = 0.02
    """std of the tangent step of the normal prior, in normalised units"""
    normal_smoothness_start: Annotated[float, Range(0, 1)] = 0.0
    """fraction of the steps before which the normal prior is off: smoothing from the start keeps the
    surface from bending into hollows (it lids a bowl), so it can wait until the topology is settled"""
    mask_weight: Annotated[float, Range(0)] = 0.1
    """weight of the mask loss, binary cross-entropy of the rendered opacity (NeuS: 0.1)"""
    anneal_end: Annotated[float, Range(0, 1)] = 0.2
    """fraction of the steps over which NeuS's cosine annealing goes from 0 to 1"""
    coarse_to_fine: Annotated[float, Range(0, 1)] = 0.0
    """fraction of the steps over which the hash-grid levels are switched on one after another,
    from ``start_levels`` (Neuralangelo's coarse-to-fine; 0: all levels from the start). The
    coarse levels settle the topology (a bowl's hollow) before the fine ones add detail"""
    start_levels: Annotated[int, Range(1, 32)] = 4
    """hash-grid levels active at the first step when ``coarse_to_fine`` > 0"""
    init_radius: Annotated[float, Range(0, 1, lo_open=True)] = 0.5
    """radius of the sphere the SDF starts as, in normalised units"""
    feature_dim: Annotated[int, Range(1, 4096)] = 16
    """size of the geometric feature vector f (paper: 512)"""
    sdf: NetworkConfig = field(default_factory=NetworkConfig)
    """the SDF network"""
    color: NetworkConfig = field(default_factory=NetworkConfig)
    """the colour network (its encoding is used only with ``appearance_encoding``)"""
    appearance_encoding: bool = False
    """the colour network encodes the point with ``color.encoding`` of its own, besides the SDF's
    feature vector: texture then need not live in the SDF's encoding, where it bends the surface"""
    exposure: Literal["shared", "per_view"] = "shared"
    """``per_view``: a learned RGB gain per training view multiplies the rendered colour, as the fit's
    ``exposure`` does (:mod:`nefii.fit.exposure`: centred over the views; started at 1, the images tell them
    apart within a few thousand steps): photos whose exposure and white balance drift from view to view,
    which one colour network would otherwise explain by bending the surface"""
    view_freqs: Annotated[int, Range(0, 32)] = 4
    """Fourier frequencies of the view direction fed to the colour network (NeuS: 4); fewer leave less
    room to fake geometry by view-dependent colour"""
    mesh_resolution: Annotated[int, Range(8, 2048)] = 256
    """marching-cubes grid resolution over the unit cube"""
    min_component: Annotated[float, Range(0, 1)] = 0.01
    """connected components with fewer than this fraction of the mesh's faces are dropped (floaters)"""
    from_mesh_points: Annotated[int, Range(1)] = 8192
    """``--from-mesh``: sampled points per step"""
    seed: Annotated[int, Range(0, 2**63 - 1)] = 0
    """seeds parameters, ray batches and samples"""
    checkpoint_every_s: Annotated[float, Range(0)] = 120.0
    """seconds between checkpoints"""
    max_image_side: Annotated[int, Range(0, 1 << 16)] = 512
    """training images whose larger side exceeds this many pixels are averaged down by the smallest integer
    factor that fits, intrinsics with them (:mod:`nefii.data.downscale`); 0: never"""
    threads: Annotated[int, Range(0, 4096)] = 0
    """CPU threads for torch (0: the cores this process may use)"""

    def __post_init__(self) -> None:
        """Every value checked (:func:`nefii.config_tools.validate`) before any data is read."""
        validate(self)
        check_memory(geometry_memory_bytes(self), "the geometry stage", "batch_rays, samples, importance, "
                     "mesh_resolution, the networks' hidden/layers or the encodings' log2_table_size/levels")


def geometry_memory_bytes(cfg: GeometryConfig) -> float:
    """A rough upper estimate of a step's memory (parameters four times over, activations at every sample
    along the rays, kept for the backward pass) and of marching cubes' grid: it only has to catch sizes no
    machine holds."""
    sdf_params, sdf_act = network_numbers(cfg.sdf)
    color_params, color_act = network_numbers(cfg.color)
    samples = cfg.batch_rays * (cfg.samples + cfg.importance + cfg.background_samples) + cfg.area_points
    activations = 3 * samples * (sdf_act + color_act + cfg.feature_dim)
    grid = 8 * (cfg.mesh_resolution + 1) ** 3
    return 4.0 * (4 * (sdf_params + color_params) + activations) + grid


_CPU: dict[str, Any] = {
    "batch_rays": 256, "samples": 16, "importance": 16, "coarse_to_fine": 0.5,
    "normal_smoothness": 0.05, "normal_smoothness_start": 0.5,
    "sdf": {"encoding": {"levels": 10, "log2_table_size": 16, "max_resolution": 128}, "hidden": 64, "layers": 1},
    "color": {"hidden": 64, "layers": 2}}

GEOMETRY_PRESETS: dict[str, dict[str, Any]] = {
    "cpu": _CPU,
    "gpu": {**_CPU, "steps": 6000, "batch_rays": 2048},
    "paper": {
        "steps": 300000, "batch_rays": 512, "samples": 64, "importance": 64, "importance_rounds": 4,
        "background_samples": 32, "lr": 5e-4, "lr_networks": 5e-4, "anneal_end": 50000 / 300000, "feature_dim": 512,
        "sdf": {"encoding": {"kind": "fourier", "fourier_freqs": 6}, "hidden": 256, "layers": 8},
        "color": {"hidden": 256, "layers": 4}, "mesh_resolution": 512,
    },
    "tiny": {
        "steps": 40, "batch_rays": 64, "samples": 8, "importance": 8, "importance_rounds": 1, "background_samples": 4,
        "coarse_to_fine": 0.5, "start_levels": 2, "area_points": 256,
        "feature_dim": 4, "mesh_resolution": 32, "from_mesh_points": 1024, "checkpoint_every_s": 60.0,
        "sdf": {"encoding": {"levels": 4, "log2_table_size": 12, "max_resolution": 32}, "hidden": 16},
        "color": {"hidden": 16, "layers": 1},
    },
}
"""``cpu``: hash-grid SDF for 2 CPU cores; ``gpu``: the ``cpu`` networks at 8 times the rays a step and a third of the
steps, for one GPU, where a step of either costs about the same (kernel launches): fits on its surfaces at least as
good as on the ``cpu`` preset's (two seeds, four scenes: albedo 26.0 against 25.8 dB) in a third of the time there
(docs/experiments.md, 2026-11-30); ``paper``: NeuS's networks (8x256 SDF MLP, 6 frequencies) for a GPU; ``tiny``:
tests."""


def resolve_geometry_config(preset: str, overrides: list[str]) -> GeometryConfig:
    """The preset, then ``key=value`` overrides with dotted keys (``sdf.hidden=128``)."""
    if preset not in GEOMETRY_PRESETS:
        raise KeyError(f"unknown preset {preset!r} (known: {', '.join(GEOMETRY_PRESETS)})"
                       f"{nearest(preset, GEOMETRY_PRESETS)}")
    values = dataclasses.asdict(GeometryConfig())
    _update(values, {**GEOMETRY_PRESETS[preset], "preset": preset})
    apply_overrides(values, overrides)
    return geometry_config_from_dict(values)


def _update(values: dict[str, Any], patch: dict[str, Any]) -> None:
    for k, v in patch.items():
        if k not in values:
            raise KeyError(f"unknown config field {k}")
        if isinstance(v, dict):
            _update(values[k], v)
        else:
            values[k] = v


def geometry_config_from_dict(values: dict[str, Any]) -> GeometryConfig:
    """Rebuild the (nested) dataclass from ``dataclasses.asdict`` output; unknown keys raise ``KeyError``."""
    base = dataclasses.asdict(GeometryConfig())
    _update(base, values)
    return dataclass_from_dict(GeometryConfig, base)
