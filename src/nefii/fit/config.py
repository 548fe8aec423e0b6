"""Fit configuration: nested dataclasses with a docstring per field, presets in one place.

The resolved config is saved as ``RUN/config.json`` and read back through the same classes
(:func:`config_from_dict`), so a run can always be reproduced from its folder.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from ..config_tools import Range, apply_overrides, check_memory, dataclass_from_dict, nearest, validate
from ..render.brdf import BRDFModel


@dataclass
class EncodingConfig:
    kind: Literal["hashgrid", "fourier"] = "hashgrid"
    """``hashgrid`` (fast on a CPU) or ``fourier`` (the paper's positional encoding)"""
    levels: Annotated[int, Range(1, 32)] = 12
    """hash grid: number of resolution levels"""
    features_per_level: Annotated[int, Range(1, 16)] = 2
    """hash grid: features stored per level"""
    log2_table_size: Annotated[int, Range(4, 26)] = 16
    """hash grid: entries per level table, as a power of two"""
    base_resolution: Annotated[int, Range(1, 1 << 16)] = 8
    """hash grid: coarsest grid resolution (over the scene box)"""
    max_resolution: Annotated[int, Range(1, 1 << 16)] = 256
    """hash grid: finest grid resolution"""
    fourier_freqs: Annotated[int, Range(0, 32)] = 10
    """fourier: frequencies per coordinate (paper: 10 for the material, 10 for the cache)"""


@dataclass
class NetworkConfig:
    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    """how points are encoded"""
    hidden: Annotated[int, Range(1, 4096)] = 64
    """hidden width of the MLP"""
    layers: Annotated[int, Range(0, 64)] = 2
    """hidden layers of the MLP (paper: 8 x 512 for the material, 4 x 512 for the cache)"""


@dataclass
class LightConfig:
    kind: Literal["sg", "envmap"] = "sg"
    """``sg``: 128 spherical Gaussians (the paper); ``envmap``: an equirectangular grid (ablation, Fig. 5)"""
    num_lobes: Annotated[int, Range(1, 4096)] = 128
    """SG lobes"""
    sharpness_min: Annotated[float, Range(0, 1e6, lo_open=True)] = 5.0
    """initial sharpness of the widest lobes"""
    sharpness_max: Annotated[float, Range(0, 1e6, lo_open=True)] = 3000.0
    """initial sharpness of the sharpest lobes (a 1-degree sun needs thousands)"""
    init_radiance: Annotated[float, Range(0, 1e6, lo_open=True)] = 0.5
    """initial environment radiance, spread over the lobes"""
    init: Literal["shading", "uniform"] = "shading"
    """SG start: ``shading`` (non-negative least squares of the pixels' diffuse shading and shadows over
    1024 directions, see nefii.fit.light_init) or ``uniform`` (Fibonacci axes, constant radiance)"""
    sharpness_init_peak: Annotated[float, Range(0, 1e6, lo_open=True)] = 800.0
    """shading init: sharpness of the lobes put on bright directions (a sun)"""
    envmap_height: Annotated[int, Range(2, 4096)] = 32
    """envmap: rows of the learnable equirectangular grid (columns: twice as many)"""


@dataclass
class FitConfig:
    preset: Literal["cpu", "gpu", "paper", "tiny"] = "cpu"
    """the preset these values started from"""
    steps: Annotated[int, Range(1)] = 3000
    """optimisation steps (observed and unobserved together)"""
    batch_pixels: Annotated[int, Range(1)] = 1024
    """object pixels per observed step"""
    background_pixels: Annotated[int, Range(0)] = 256
    """background pixels per observed step (Eq. 7, third term)"""
    num_samples: Annotated[int, Range(1, 4096)] = 8
    """N estimator samples per point; each draws 3 directions (cosine, GGX, SG): paper N = 64"""
    unobserved_points: Annotated[int, Range(1)] = 1024
    """secondary hits per unobserved step (Eq. 8)"""
    unobserved_every: Annotated[int, Range(1)] = 10
    """K: every K-th step trains on unobserved rays instead (paper K = 10)"""
    unobserved: bool = True
    """ablation: train on unobserved rays at all"""
    unobserved_material: Literal["all", "albedo", "none"] = "none"
    """what of the material Eq. 8 moves at the secondary hits: ``all`` (the official code: neither side
    detached), ``albedo`` (roughness held fixed there) or ``none`` (Eq. 8 trains the cache and the light only).
    The cache sees a point's outgoing radiance through a few Fourier frequencies of direction, so pulling
    roughness towards it blurs a glossy lobe and kept the fit's roughness rough (docs/experiments.md,
    2026-11-25); pulling the albedo towards it cost leaning and the corner 0.6-1.2 dB (2026-11-29, sixteenth
    session)"""
    unobserved_light: Literal["all", "resolvable"] = "resolvable"
    """what of the SG light Eq. 8 trains: ``all`` (the official code) or the lobes the cache can hold in direction
    (``RadianceCache.max_lobe_sharpness``; a sharper lobe, a sun, is a constant of Eq. 8's gradient). The cache
    cannot hold a sharp lobe's glossy reflection, so with neither side detached Eq. 8 widened and drained the
    sun that the light initialisation had found (docs/experiments.md, 2026-11-27, fifth session)"""
    indirect: bool = True
    """ablation: secondary hits see the radiance cache (off: black)"""
    visibility: bool = True
    """ablation: trace secondary rays (off: every direction sees the environment, PhySG-style)"""
    roughness_warmup: Annotated[float, Range(0, 1)] = 0.4
    """fraction of the steps with roughness held at 0.5 (paper: 50 of 120 epochs)"""
    lr: Annotated[float, Range(0, 10, lo_open=True)] = 5e-3
    """Adam learning rate for the networks (paper 5e-4 at 8x512 MLPs; a hash grid wants ~1e-2)"""
    lr_light: Annotated[float, Range(0, 10)] = 2e-2
    """Adam learning rate for the environment's radiance (SG amplitudes, or the env-map grid)"""
    lr_light_shape: Annotated[float, Range(0, 10)] = 1e-3
    """Adam learning rate for the SG axes and log-sharpness. Adam moves every parameter by about its
    learning rate per step whatever the gradient's size, so at 2e-2 a sun lobe's axis random-walks ~1 degree
    a step on noisy gradients and the sun found by the light initialisation is lost within 150 steps"""
    lr_decay: Annotated[float, Range(0, 1, lo_open=True)] = 0.1
    """learning rates fall exponentially to this fraction at the last step"""
    beta1: Annotated[float, Range(0)] = 1.0
    """weight of the cache's own colour loss (Eq. 7)"""
    beta2: Annotated[float, Range(0)] = 1.0
    """weight of the background loss (Eq. 7)"""
    loss: Literal["l1", "l2", "l2_pair"] = "l2_pair"
    """distance of the colour losses: ``l1`` (Eq. 7, 8), ``l2`` (squared), or ``l2_pair`` (the product of the
    errors of two independent half-sample estimates: unbiased for the squared error of the estimate's mean,
    where l1/l2 of one noisy estimate also penalise its variance and so dim a sun; see docs/design.md)"""
    tonemap: Literal["none", "log1p"] = "log1p"
    """colour space of the losses: ``none`` (linear, as Eq. 7) or ``log1p`` (keeps highlights from dominating)"""
    smooth_albedo: Annotated[float, Range(0)] = 0.005
    """weight of an L1 prior between the albedo at a point and at a jittered neighbour (0: off, as the paper):
    keeps the hash grid from memorising Monte Carlo noise"""
    smooth_albedo_end: Annotated[float, Range(0, 1)] = 0.0
    """the albedo prior's weight at the last step, as a fraction of ``smooth_albedo``: it falls linearly from
    the end of the roughness warm-up (1: constant). Early on the prior keeps the light's ambiguity out of the
    albedo while the light settles; faded, it stops flattening texture (docs/experiments.md, 2026-11-27, fourth
    session)"""
    smooth_radius: Annotated[float, Range(0, 1)] = 0.01
    """jitter of the smoothness prior, as a fraction of the scene's bounding-box diagonal"""
    light_prior: Annotated[float, Range(0)] = 2e-4
    """weight of a prior that darkens the light where the object barely sees it (0: off, as the paper;
    :mod:`nefii.fit.light_prior`)"""
    light_solve_every: Annotated[int, Range(0)] = 100
    """every this many steps the SG amplitudes are set to Eq. 7's minimiser given the rest of the model, instead
    of only following Adam (0: never, as the paper; :mod:`nefii.fit.light_solve`). Only with SG lobes and
    ``loss = l2_pair`` (the solve minimises that loss); otherwise no solve runs"""
    light_solve_pixels: Annotated[int, Range(1)] = 8192
    """training pixels (and as many background pixels) each light solve reads"""
    exposure: Literal["shared", "per_view"] = "shared"
    """``shared``: every view shares one exposure and white balance (renders, a camera on manual); ``per_view``:
    a learned RGB gain per training view, their geometric mean held at 1 (phone photos: auto exposure and white
    balance; :mod:`nefii.fit.exposure`). Eval and relight render without gains"""
    max_image_side: Annotated[int, Range(0, 1 << 16)] = 512
    """training images whose larger side exceeds this many pixels are averaged down by the smallest integer
    factor that fits, intrinsics with them (a phone's 4032 x 3024 photos; :mod:`nefii.data.downscale`); 0: never"""
    secondary_buffer: Annotated[int, Range(1)] = 65536
    """secondary hits kept for the unobserved step"""
    ray_offset: Annotated[float, Range(0, 0.1)] = 1e-4
    """secondary-ray origin offset, as a fraction of the scene's bounding-box diagonal (training, eval and the
    light initialisation)"""
    seed: Annotated[int, Range(0, 2**63 - 1)] = 0
    """seeds parameters, pixel batches and direction samples"""
    geometry_mode: Literal["mesh", "sdf"] = "mesh"
    """with ``nefii fit --geometry GEO``: ``mesh`` ray-casts GEO/mesh.ply (fast); ``sdf`` sphere-traces GEO's
    SDF and feeds its feature vector f to the material and the cache, as the paper does"""
    material: NetworkConfig = field(default_factory=NetworkConfig)
    """material field M"""
    brdf: BRDFModel = field(default_factory=BRDFModel)
    """the BRDF's diffuse lobe and shadowing term (``paper``: the official code's Lambert and Schlick-GGX, which
    pulls a fit's roughness glossy under an environment; docs/experiments.md, 2026-11-25)"""
    material_offset: Annotated[float, Range(0, 1)] = 0.0
    """M encodes ``x + offset * n`` (n the shading normal), offset as a fraction of the scene's bounding-box
    diagonal: the faces of a thin wall then do not share the encoding's coarse cells (0: encode x, the paper)"""
    material_offset_reconstructed: Annotated[float, Range(0, 1)] = 0.0
    """``material_offset`` used instead when the geometry is a reconstruction (``--geometry GEO``, the output of
    ``nefii geometry``), whose normals are less exact: an offset turns a normal error e into a lateral error
    ``offset * sin(e)`` of the lookup"""
    normal_smoothing_reconstructed: Annotated[float, Range(0, 1)] = 0.0
    """with ``--geometry GEO`` in ``mesh`` mode: the mesh's vertex normals are smoothed along its edges to this
    lateral scale (a fraction of the bounding-box diagonal; 0: none), against the reconstruction's bumps"""
    lookup_smoothing_reconstructed: Annotated[float, Range(0, 1)] = 0.0
    """with ``--geometry GEO`` in ``mesh`` mode: the material lookup ``x + offset * n`` takes n from the mesh's
    vertex normals smoothed to this lateral scale (a fraction of the diagonal; 0: the shading normals), so the
    offset only says which side of a wall a point is on and does not carry the reconstruction's normal noise"""
    cache: NetworkConfig = field(default_factory=NetworkConfig)
    """radiance cache L"""
    cache_dir_freqs: Annotated[int, Range(0, 32)] = 4
    """Fourier frequencies of the cache's direction inputs (paper: 4)"""
    light: LightConfig = field(default_factory=LightConfig)
    """environment light"""
    checkpoint_every_s: Annotated[float, Range(0)] = 120.0
    """seconds between checkpoints"""
    preview_every: Annotated[int, Range(0)] = 500
    """steps between preview images (0: none)"""
    threads: Annotated[int, Range(0, 4096)] = 0
    """CPU threads for torch (0: the cores this process may use)"""

    def __post_init__(self) -> None:
        """Every value checked (:func:`nefii.config_tools.validate`), then what no single field can say."""
        validate(self)
        if self.loss == "l2_pair" and self.num_samples < 2:
            raise ValueError("num_samples: loss l2_pair needs at least 2 (two independent half estimates)")
        if self.light.sharpness_min > self.light.sharpness_max:
            raise ValueError(f"light.sharpness_min: {self.light.sharpness_min:g} is above light.sharpness_max "
                             f"{self.light.sharpness_max:g}")
        check_memory(fit_memory_bytes(self), "the fit", "batch_pixels, unobserved_points, num_samples, the "
                     "networks' hidden/layers or the encodings' log2_table_size/levels")


def network_numbers(net: NetworkConfig) -> tuple[int, int]:
    """(parameters, activations per point) of a field: its encoding table and its MLP."""
    enc = net.encoding
    if enc.kind == "hashgrid":
        table, width = enc.levels * 2**enc.log2_table_size * enc.features_per_level, enc.levels * enc.features_per_level
    else:
        table, width = 0, 3 * (2 * enc.fourier_freqs + 1)
    mlp = (width + 64) * net.hidden + max(net.layers - 1, 0) * net.hidden**2
    return table + mlp, width + net.hidden * max(net.layers, 1)


def fit_memory_bytes(cfg: FitConfig) -> float:
    """A rough upper estimate of a fit step's memory: the parameters four times over (weights, gradients,
    Adam's two moments), the activations kept for the backward pass at every estimator direction, the SG
    light's lobe values there (kept from the light pdf for the escaped rays' radiance), the secondary-hit
    buffer. It only has to catch sizes no machine holds, before any data is read."""
    m_params, m_act = network_numbers(cfg.material)
    c_params, c_act = network_numbers(cfg.cache)
    points = max(cfg.batch_pixels, cfg.unobserved_points)
    directions = points * cfg.num_samples * 3
    activations = 2 * (points * 2 * m_act + directions * c_act) + directions * cfg.light.num_lobes
    env = 6 * cfg.light.envmap_height**2 + 7 * cfg.light.num_lobes
    return 4.0 * (4 * (m_params + c_params + env) + activations + 32 * cfg.secondary_buffer)


PRESETS: dict[str, dict[str, Any]] = {
    "cpu": {"material": {"encoding": {"max_resolution": 128}}, "material_offset": 0.04,
            "material_offset_reconstructed": 0.04, "normal_smoothing_reconstructed": 0.005,
            "lookup_smoothing_reconstructed": 0.04},
    "gpu": {"batch_pixels": 8192, "background_pixels": 2048, "num_samples": 16, "unobserved_points": 8192,
            "secondary_buffer": 1 << 19, "light_solve_pixels": 32768,
            "material": {"encoding": {"max_resolution": 512, "log2_table_size": 18}},
            "cache": {"encoding": {"log2_table_size": 18}},
            "material_offset": 0.04, "material_offset_reconstructed": 0.04, "normal_smoothing_reconstructed": 0.005,
            "lookup_smoothing_reconstructed": 0.04},
    "paper": {
        "steps": 60000, "batch_pixels": 2048, "num_samples": 64, "lr": 5e-4, "lr_light": 5e-3,
        "tonemap": "none", "loss": "l1", "smooth_albedo": 0.0, "light_prior": 0.0, "light_solve_every": 0,
        "roughness_warmup": 50 / 120,
        "material": {"encoding": {"kind": "fourier", "fourier_freqs": 10}, "hidden": 512, "layers": 8},
        "cache": {"encoding": {"kind": "fourier", "fourier_freqs": 10}, "hidden": 512, "layers": 4},
        "light": {"sharpness_max": 3000.0}, "brdf": {"diffuse": "lambert", "shadowing": "schlick"},
        "unobserved_material": "all", "unobserved_light": "all",
    },
    "tiny": {
        "steps": 20, "batch_pixels": 64, "background_pixels": 16, "num_samples": 2, "unobserved_points": 64,
        "unobserved_every": 5, "checkpoint_every_s": 60.0, "preview_every": 0, "secondary_buffer": 4096,
        "material": {"encoding": {"levels": 4, "log2_table_size": 12, "max_resolution": 32}, "hidden": 16},
        "cache": {"encoding": {"levels": 4, "log2_table_size": 12, "max_resolution": 32}, "hidden": 16},
        "light": {"num_lobes": 16}, "material_offset": 0.04, "material_offset_reconstructed": 0.01,
        "normal_smoothing_reconstructed": 0.005,
    },
}
"""``cpu``: designed for 2 CPU cores (hash grids, small MLPs, N = 8; the side-aware material offset, and on a
reconstruction the lookup's normals smoothed so the offset does not carry its normal noise); ``gpu``: the ``cpu``
preset's method at 16 times its samples per step (8 times the pixels, N = 16) and a material grid fine enough for
512 x 512 views, for one GPU (benchmarks/results/gpu.md); ``paper``: the
paper's networks and sample counts and the official code's BRDF, for a GPU; ``tiny``: tests. What each choice measured is logged in
docs/experiments.md."""


def config_from_dict(values: dict[str, Any]) -> FitConfig:
    """Build a FitConfig from a (possibly partial, nested) dict; unknown keys raise ``KeyError``."""
    return dataclass_from_dict(FitConfig, values)


def saved_config_from_dict(values: dict[str, Any]) -> FitConfig:
    """A config a run saved: a setting missing from it reads back as the behaviour the run was fitted with,
    not today's default (the official BRDF before ``brdf`` existed; Eq. 8 training all of the material before
    ``unobserved_material`` existed; no light prior before ``light_prior`` existed; a constant albedo prior before
    ``smooth_albedo_end`` existed; Eq. 8 training every lobe of the light before ``unobserved_light`` existed)."""
    return config_from_dict({"brdf": {"diffuse": "lambert", "shadowing": "schlick"},
                             "unobserved_material": "all", "light_prior": 0.0, "smooth_albedo_end": 1.0,
                             "unobserved_light": "all", **values})


def config_to_dict(cfg: FitConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def resolve_config(preset: str, overrides: list[str]) -> FitConfig:
    """The preset, then ``key=value`` overrides with dotted keys (``material.hidden=128``)."""
    if preset not in PRESETS:
        raise KeyError(f"unknown preset {preset!r} (known: {', '.join(PRESETS)}){nearest(preset, PRESETS)}")
    values = config_to_dict(config_from_dict({**PRESETS[preset], "preset": preset}))
    apply_overrides(values, overrides)
    return config_from_dict(values)
