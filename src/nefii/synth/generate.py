"""``synthesize``: render one built-in scene into a complete dataset folder, atomically.

Order of work: validate, build geometry and textures, bake every environment twice (nefii's
equirect for the files, Mitsuba's grid for the renderer), place cameras, then render into a
temporary folder beside the output and rename it into place at the very end.
"""
from __future__ import annotations

import hashlib
import importlib.metadata as md
import platform
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from ..io.atomic import atomic_dir
from ..io.exr import write_exr
from . import cameras, layout
from .envmaps import bake_equirect
from .meshes import write_ply
from .textures import write_material
from .mitsuba_backend import MitsubaRenderer, bake_for_mitsuba, import_mitsuba, select_variant
from .scenes import SCENES, SceneSpec, build_scene
from .skies import ENVIRONMENTS, get_environment
from .textures import ALBEDO_RANGE, ROUGHNESS_RANGE

FORMAT = "nefii-synth/1"


@dataclass(frozen=True)
class SynthSettings:
    """Everything that decides what ``nefii synth`` renders; saved in ``scene.json``."""

    scene: str
    """built-in scene name (``nefii synth --list``)"""
    res: int = 256
    """image width and height in pixels"""
    views: int = 100
    """training views"""
    test_views: int = 20
    """test views (with ground-truth maps and relighting)"""
    spp: int = 256
    """samples per pixel of every render (no clamping: noise falls as 1/sqrt(spp))"""
    seed: int = 0
    """seeds the camera spiral's azimuth and every render's sampler (not geometry or materials)"""
    env_height: int = 1024
    """height of envmap.exr and relight/*.exr (width is twice); Mitsuba's grid has one row more"""
    environment: str = ""
    """the built-in environment the training and test views are lit by ("": the scene's own)"""
    fov_x_deg: float = 40.0
    """horizontal field of view"""
    max_depth: int = 12
    """longest light path in vertices, as Mitsuba counts (Russian roulette from depth 5)"""

    def validate(self) -> None:
        """Raise :class:`InputError` naming the first bad setting."""
        if self.scene not in SCENES:
            raise InputError(None, f"unknown scene {self.scene!r}; built-in scenes: {', '.join(SCENES)}")
        if self.environment and self.environment not in ENVIRONMENTS:
            raise InputError(None, f"unknown environment {self.environment!r}; built-in environments: "
                                   f"{', '.join(ENVIRONMENTS)}")
        for name, value, lo, hi in (("--res", self.res, 8, 8192), ("--views", self.views, 1, 100_000),
                                    ("--test-views", self.test_views, 1, 100_000), ("--spp", self.spp, 1, 1 << 20),
                                    ("--seed", self.seed, 0, (1 << 31) - 1), ("--env-height", self.env_height, 8, 16384)):
            if not lo <= value <= hi:
                raise InputError(None, f"{name} must be between {lo} and {hi}, got {value}")


@dataclass
class _Stats:
    clipped: int = 0
    layer_gap: list[float] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)


@lru_cache(maxsize=16)
def _baked(env_name: str, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(nefii equirect map, Mitsuba's grid) of an environment; cached, as scenes share them."""
    env = get_environment(env_name)
    return bake_equirect(env, height, 2 * height), bake_for_mitsuba(env, height + 1, 2 * height)


def lit_by(spec: SceneSpec, environment: str) -> SceneSpec:
    """The scene under another built-in ``environment`` ("": as it is). Its relighting pair keeps the scene's
    other environments, with the scene's own taking the place of the new one if that was among them."""
    if not environment or environment == spec.environment:
        return spec
    relight = tuple(spec.environment if name == environment else name for name in spec.relight)
    return replace(spec, environment=environment, relight=relight)


def render_seed(seed: int, split: str, index: int, kind: str) -> int:
    """Independent sampler seeds for every (split, view, kind) of a run."""
    return int(np.random.SeedSequence([seed, ("train", "test").index(split), index,
                                       ("rgba", "layers", "relight0", "relight1").index(kind)]).generate_state(1)[0])


def check_output_folder(out: Path) -> None:
    """Refuse to replace anything but an earlier ``nefii synth`` output."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "scene.json").is_file():
        raise InputError(out, "is a non-empty folder that is not a nefii synth output; remove it or choose another --out")


def synthesize(settings: SynthSettings, out: str | Path, *, progress: bool = True) -> Path:
    """Render ``settings.scene`` into ``out`` (replacing an earlier output there as a whole)."""
    settings.validate()
    out = Path(out)
    check_output_folder(out)
    import_mitsuba()  # fail early, before minutes of baking, if Mitsuba is missing
    stats, t0 = _Stats(), time.time()
    scene = build_scene(settings.scene)
    spec = lit_by(scene.spec, settings.environment)
    env_names = (spec.environment, *spec.relight)
    maps = {name: _baked(name, settings.env_height) for name in env_names}
    rig = cameras.make_rig(settings.views, settings.test_views, settings.res, scene.radius, spec.elevation_deg,
                           settings.seed, settings.fov_x_deg)
    renderer = MitsubaRenderer(scene.atlas, {n: m[1] for n, m in maps.items()}, settings.res, settings.res,
                               settings.fov_x_deg, settings.max_depth)
    stats.seconds["setup"] = time.time() - t0

    with atomic_dir(out) as tmp:
        write_ply(tmp / "mesh.ply", scene.atlas.mesh)
        write_material(tmp / "material.npz", scene.atlas)
        write_exr(tmp / "envmap.exr", maps[spec.environment][0])
        for name in spec.relight:
            write_exr(tmp / "relight" / f"{name}.exr", maps[name][0])
        t1 = time.time()
        jobs = [("train", k, p) for k, p in enumerate(rig.train)] + [("test", k, p) for k, p in enumerate(rig.test)]
        for split, k, pose in tqdm(jobs, desc=f"synth {settings.scene}", unit="view", disable=not progress):
            _render_view(renderer, settings, spec, tmp, split, k, pose, stats)
        stats.seconds["render"] = time.time() - t1
        layout.write_json(tmp / "transforms_train.json", cameras.transforms_json(rig, rig.train, "train"))
        layout.write_json(tmp / "transforms_test.json", cameras.transforms_json(rig, rig.test, "test"))
        layout.write_json(tmp / "scene.json", scene_record(settings, scene, spec, rig, renderer, maps, stats))
    return out


def _render_view(renderer: MitsubaRenderer, settings: SynthSettings, spec, root: Path, split: str, k: int,
                 pose: np.ndarray, stats: _Stats) -> None:
    renderer.set_camera(pose)
    rgba = renderer.render_rgba(spec.environment, settings.spp, render_seed(settings.seed, split, k, "rgba"))
    stats.clipped += layout.write_rgba(root / split, f"r_{k}", rgba)
    if split != "test":
        return
    layers = renderer.render_layers(spec.environment, settings.spp, render_seed(settings.seed, split, k, "layers"))
    layout.write_test_maps(root / split, f"r_{k}", layers, rgba[..., 3], pose)
    total = float(rgba[..., :3].sum())
    if total > 0:
        stats.layer_gap.append(abs(float(layers["full"].sum()) - total) / total)
    for j, name in enumerate(spec.relight):
        relit = renderer.render_rgba(name, settings.spp, render_seed(settings.seed, split, k, f"relight{j}"))
        stats.clipped += layout.write_rgba(root / "relight" / name, f"r_{k}", relit, png=False)


def _version(dist: str) -> str | None:
    try:
        return md.version(dist)
    except md.PackageNotFoundError:
        return None


def _synth_source_hash() -> str:
    """The first 12 hex digits of the SHA-256 of this package's sources (file names and contents, sorted):
    a change to the scene code shows in ``scene.json`` even when nefii's version number does not move."""
    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def synth_versions() -> dict[str, str | None]:
    """What a synthesised scene depends on beyond its settings: the scene code, the libraries that render it
    and Mitsuba's variant (llvm and scalar draw other samples). Recorded in ``scene.json``; two scenes made with
    the same settings and these values are the same."""
    return {"nefii": _version("nefii"), "synth_source": _synth_source_hash(), "python": platform.python_version(),
            "numpy": np.__version__, "torch": _version("torch"), "mitsuba": _version("mitsuba"),
            "mitsuba_variant": select_variant(), "drjit": _version("drjit"), "openexr": _version("OpenEXR"),
            "opencv": _version("opencv-python-headless"), "platform": sys.platform}


def _env_record(name: str, image: np.ndarray, file: str) -> dict:
    env = get_environment(name)
    sun = None if env.sun is None else {
        "direction": list(env.sun.direction), "angular_diameter_deg": env.sun.angular_diameter_deg,
        "radiance": list(env.sun.radiance), "solid_angle_sr": env.sun.solid_angle()}
    return {"name": name, "file": file, "description": env.description, "lighting": env.lighting,
            "height": image.shape[0], "width": image.shape[1], "sun": sun}


def scene_record(settings: SynthSettings, scene, spec: SceneSpec, rig, renderer: MitsubaRenderer, maps: dict,
                 stats: _Stats) -> dict:
    """The content of ``scene.json`` (``spec``: the scene as lit, :func:`lit_by`)."""
    atlas = scene.atlas
    gap = stats.layer_gap
    return {
        "format": FORMAT,
        "scene": spec.name, "summary": spec.summary,
        "settings": asdict(settings),
        "environment": {**_env_record(spec.environment, maps[spec.environment][0], "envmap.exr"),
                        "mapping": "equirectangular, nefii.render.equirect: row 0 = +Z, u = 0.5 - atan2(y, x) / 2pi, "
                                   "texel = mean over its pixel cell (sun disc integrated exactly)"},
        "relight": [{**_env_record(n, maps[n][0], f"relight/{n}.exr"), "views": f"relight/{n}/r_K.exr"}
                    for n in spec.relight],
        "mesh": {"file": "mesh.ply", "vertices": len(atlas.mesh.vertices), "triangles": len(atlas.mesh.faces),
                 "bounding_radius": scene.radius,
                 "parts": [{"name": n, "triangles": f} for n, f in zip(atlas.part_names, atlas.part_faces)]},
        "material": {"bsdf": "mitsuba principled", "specular": 0.5, "f0": 0.04, "metallic": 0.0, "spec_tint": 0.0,
                     "sheen": 0.0, "clearcoat": 0.0, "spec_trans": 0.0, "anisotropic": 0.0,
                     "roughness": "perceptual r, GGX alpha = r^2", "roughness_range": list(ROUGHNESS_RANGE),
                     "base_color_range": list(ALBEDO_RANGE),
                     "textures": f"procedural bitmaps {atlas.base_color.shape[1]}x{atlas.base_color.shape[0]}, "
                                 "bilinear"},
        "cameras": {"model": "pinhole", "fov_x_deg": settings.fov_x_deg, "distance": rig.distance,
                    "elevation_deg": list(spec.elevation_deg), "look_at": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0],
                    "train": len(rig.train), "test": len(rig.test),
                    "transform_matrix": "camera-to-world, OpenGL/Blender camera axes (x right, y up, looking "
                                        "down -z), world Z up"},
        "renderer": {"name": "mitsuba", "variant": renderer.variant, "integrator": "path",
                     "max_depth": settings.max_depth, "rr_depth": 5, "sampler": "independent",
                     "pixel_filter": "box", "spp": settings.spp, "hide_emitters": True,
                     "layers_integrator": "nefii.synth.mitsuba_layers (specular lobe at the first hit, "
                                          "Mitsuba path tracing after it)"},
        "noise": {"clamped": False, "firefly_policy": "none: no clamping, unbiased; sun fireflies on glossy "
                  "parts fall with spp (use --spp 256 or more for ground truth)",
                  "float16_values_clipped_at_65504": stats.clipped},
        "checks": {"test_view_relative_gap_full_layers_vs_path": {
            "mean": float(np.mean(gap)) if gap else None, "max": float(np.max(gap)) if gap else None,
            "meaning": "|sum(specular + diffuse) - sum(r_K rgb)| / sum(r_K rgb) per test view; independent "
                       "samples, so it is Monte Carlo noise plus any bias"}},
        "versions": synth_versions(),
        "timing_s": stats.seconds,
    }
