"""Everything that touches Mitsuba 3: variant choice, its env-map grid, the scene, render passes.

Facts this module relies on (Mitsuba 3.9.1 / drjit 1.5.0), each checked by a test:

* ``llvm_ad_rgb`` needs libLLVM. Debian's libLLVM-15 *aborts the process* at the first kernel
  (``LLVM ERROR: Cannot select ... fminimum``) and 14 is refused; 19 works. So we point
  ``DRJIT_LIBLLVM_PATH`` at a libLLVM >= 16 before mitsuba is imported, try the variant in a
  *subprocess* first (an abort there cannot take us down), and otherwise fall back to
  ``scalar_rgb`` (3-4x slower; the Python integrator much more so) with a warning.
* The camera has +X to the left: ``to_world = c2w_gl @ diag(-1, 1, -1, 1)``.
* ``envmap`` texels sit pole to pole: row ``i`` at ``theta = pi i / (H - 1)``, column ``j`` at
  ``u = (j + 0.5) / W`` with local direction ``(sin theta sin 2pi u, cos theta, -sin theta cos 2pi u)``
  (Y up); :data:`ENV_TO_WORLD` turns local Y into world Z. This grid differs from nefii's
  pixel-centre grid, so :func:`bake_for_mitsuba` bakes it from the procedural sky directly.
"""
from __future__ import annotations

import glob
import importlib.util
import math
import os
import re
import subprocess
import sys
import warnings
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from .envmaps import ENVMAP_HEIGHT, ENVMAP_WIDTH, Grid, bake
from .skies import Environment

ENV_TO_WORLD = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
"""Mitsuba envmap local frame (Y up) -> nefii world (Z up): a +90 deg turn about X"""

GL_TO_MITSUBA_CAMERA = np.diag([-1.0, 1.0, -1.0, 1.0])
"""``to_world = c2w_gl @ GL_TO_MITSUBA_CAMERA`` (Mitsuba cameras look down +Z with +X left)"""

LANES_PER_PASS = 1 << 20
"""samples traced per render call; larger spp is split into passes to bound memory"""

LLVM_ENV = "DRJIT_LIBLLVM_PATH"
VARIANT_ENV = "NEFII_MITSUBA_VARIANT"
"""set to ``llvm_ad_rgb`` or ``scalar_rgb`` to skip the probe"""
_PROBE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_dict({"type": "scene", "e": {"type": "constant"},
                      "s": {"type": "sphere", "bsdf": {"type": "principled", "roughness": 0.3}}})
sensor = mi.load_dict({"type": "perspective", "to_world": mi.ScalarTransform4f().translate([0, 0, -4]),
                       "film": {"type": "hdrfilm", "width": 4, "height": 4}})
img = mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "path"}), spp=4)
assert float(mi.TensorXf(img).numpy().mean()) > 0
print("ok")
"""


# ---------------------------------------------------------------- variant

def find_libllvm() -> str | None:
    """A libLLVM of version >= 16: ``$DRJIT_LIBLLVM_PATH`` if set, else the newest found."""
    if os.environ.get(LLVM_ENV):
        return os.environ[LLVM_ENV]
    found = []
    for pattern in ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
                    "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"):
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if m and int(m.group(1)) >= 16:
                found.append((int(m.group(1)), path))
    return max(found)[1] if found else None


@lru_cache(maxsize=1)
def select_variant() -> str:
    """``llvm_ad_rgb`` if it renders in a subprocess with the libLLVM we point it at, else ``scalar_rgb``."""
    forced = os.environ.get(VARIANT_ENV)
    if forced:
        if forced == "llvm_ad_rgb" and find_libllvm():
            os.environ[LLVM_ENV] = find_libllvm()
        return forced
    lib = find_libllvm()
    reason = "no libLLVM >= 16 found (apt-get install libllvm19)"
    if lib:
        env = dict(os.environ, **{LLVM_ENV: lib})
        try:
            r = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=300)
            if r.returncode == 0 and "ok" in r.stdout:
                os.environ[LLVM_ENV] = lib
                return "llvm_ad_rgb"
            lines = r.stderr.strip().splitlines() or ["no output"]
            tail = next((ln for ln in lines if "ERROR" in ln.upper()), lines[-1]).strip()
            reason = f"llvm_ad_rgb with {lib} failed in a test process (exit {r.returncode}: {tail[:200]})"
        except subprocess.TimeoutExpired:
            reason = f"llvm_ad_rgb with {lib} timed out in a test process"
    warnings.warn(f"nefii synth: {reason}; falling back to Mitsuba's scalar_rgb variant, which is much "
                  "slower. Install libLLVM 19 (apt-get install libllvm19) for llvm_ad_rgb.", RuntimeWarning,
                  stacklevel=2)
    return "scalar_rgb"


def thread_count() -> int:
    """``$OMP_NUM_THREADS`` if set, else the cores this process may use."""
    try:
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    except (KeyError, ValueError):
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def import_mitsuba():
    """Import mitsuba with the chosen variant set and drjit's thread pool sized; returns ``(mi, dr)``."""
    if importlib.util.find_spec("mitsuba") is None:  # pragma: no cover - depends on the environment
        raise SystemExit("nefii synth: error: needs Mitsuba 3, the 'synth' extra: pip install 'nefii[synth]'")
    variant = select_variant()
    import drjit as dr
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    dr.set_thread_count(thread_count())
    return mi, dr


# ---------------------------------------------------------------- env map grid

def mitsuba_uv_to_direction(u: Tensor, v: Tensor) -> Tensor:
    """World direction of Mitsuba envmap texture coordinates (``u`` without its half-texel shift)."""
    theta, phi = math.pi * v, 2.0 * math.pi * u
    st = torch.sin(theta)
    local = torch.stack([st * torch.sin(phi), torch.cos(theta), -st * torch.cos(phi)], -1)
    return local @ torch.as_tensor(ENV_TO_WORLD[:3, :3], dtype=local.dtype).T


def mitsuba_grid(height: int, width: int) -> Grid:
    """Mitsuba's envmap texels: row ``i`` at ``v = i / (H - 1)`` (its cell half a row either side,
    clipped at the poles), column ``j`` centred at ``u = (j + 0.5) / W``."""
    def centres() -> Tensor:
        v = torch.arange(height, dtype=torch.float64) / (height - 1)
        u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return mitsuba_uv_to_direction(uu, vv)

    def texel_of(d: Tensor) -> tuple[Tensor, Tensor]:
        local = d.to(torch.float64) @ torch.as_tensor(ENV_TO_WORLD[:3, :3], dtype=torch.float64)
        u = torch.remainder(torch.atan2(local[..., 0], -local[..., 2]) / (2.0 * math.pi), 1.0)
        v = torch.atan2(torch.hypot(local[..., 0], local[..., 2]), local[..., 1]) / math.pi
        return (torch.round(v * (height - 1)).long().clamp(0, height - 1),
                torch.floor(u * width).long().clamp(0, width - 1))

    def row_solid_angle() -> Tensor:
        theta = math.pi * torch.arange(height, dtype=torch.float64) / (height - 1)
        half = 0.5 * math.pi / (height - 1)
        lo, hi = (theta - half).clamp(0.0, math.pi), (theta + half).clamp(0.0, math.pi)
        return (2.0 * math.pi / width) * (torch.cos(lo) - torch.cos(hi))

    return Grid(height, width, centres, texel_of, row_solid_angle)


def bake_for_mitsuba(env: Environment, height: int = ENVMAP_HEIGHT + 1, width: int = ENVMAP_WIDTH) -> np.ndarray:
    """The ``(height, width, 3)`` bitmap Mitsuba's ``envmap`` reads, baked on its own texel grid."""
    return bake(env, mitsuba_grid(height, width))


# ---------------------------------------------------------------- scene

def _bitmap_texture(mi, data: np.ndarray) -> dict:
    img = np.ascontiguousarray(data if data.ndim == 3 else data[..., None], dtype=np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(img), "raw": True, "filter_type": "bilinear",
            "wrap_mode": "clamp"}


def principled(mi, base_color: dict, roughness: dict) -> dict:
    """The one BSDF of every scene: dielectric principled, specular 0.5 (F0 = 0.04), metallic 0."""
    return {"type": "principled", "base_color": base_color, "roughness": roughness,
            "specular": 0.5, "metallic": 0.0}


def build_mesh(mi, vertices, faces, normals, uv, bsdf):
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh("object", len(vertices), len(faces), props=props, has_vertex_normals=True,
                   has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    for key, data, dtype in (("vertex_positions", vertices, np.float32), ("faces", faces, np.uint32),
                             ("vertex_normals", normals, np.float32), ("vertex_texcoords", uv, np.float32)):
        buffer_type = type(params[key])  # mi.Float in JIT variants, a dynamic array in scalar ones
        params[key] = buffer_type(np.ascontiguousarray(np.asarray(data, dtype).ravel()))
    params.update()
    return mesh


def envmap_emitter(mi, bitmap: np.ndarray) -> dict:
    return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(bitmap, dtype=np.float32)),
            "to_world": mi.ScalarTransform4f(ENV_TO_WORLD.tolist())}


# ---------------------------------------------------------------- renderer

class MitsubaRenderer:
    """One mesh with its textures under several environments, one pinhole camera moved per view.

    :meth:`render_rgba` is Mitsuba's ``path`` integrator with the environment hidden from
    camera rays: premultiplied radiance of the object, alpha = pixel coverage.
    :meth:`render_layers` is :mod:`nefii.synth.mitsuba_layers`: specular layer, full
    radiance and per-pixel ground truth, all averaged over the pixel (background 0).
    Images are ``(H, W, C)`` float32, pixel ``(0, 0)`` top left, box pixel filter.
    """

    def __init__(self, atlas, env_bitmaps: dict[str, np.ndarray], width: int, height: int,
                 fov_x_deg: float, max_depth: int = 12) -> None:
        from .mitsuba_layers import AOV_NAMES, layer_integrator

        mi, dr = import_mitsuba()
        self.mi, self.dr, self.variant = mi, dr, mi.variant()
        self.width, self.height, self.max_depth = width, height, max_depth
        self.aov_names = AOV_NAMES
        m = atlas.mesh
        base, rough = _bitmap_texture(mi, atlas.base_color), _bitmap_texture(mi, atlas.roughness)
        self.scenes = {}
        for name, bitmap in env_bitmaps.items():
            bsdf = mi.load_dict(principled(mi, base, rough))
            mesh = build_mesh(mi, m.vertices, m.faces, m.normals, m.uv, bsdf)
            self.scenes[name] = mi.load_dict({"type": "scene", "object": mesh, "env": envmap_emitter(mi, bitmap)})
        self.sensor = mi.load_dict({
            "type": "perspective", "fov": fov_x_deg, "fov_axis": "x", "near_clip": 0.01, "far_clip": 100.0,
            "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}})
        self.sensor_params = mi.traverse(self.sensor)
        self.path = mi.load_dict({"type": "path", "max_depth": max_depth, "hide_emitters": True})
        spec_twin = mi.load_dict(principled(mi, {"type": "rgb", "value": [0.0, 0.0, 0.0]}, rough))
        self.layers = layer_integrator(mi, dr, max_depth, spec_twin, mi.load_dict(rough))

    def set_camera(self, c2w_gl: np.ndarray) -> None:
        """Place the camera by its OpenGL/Blender camera-to-world matrix."""
        to_world = np.asarray(c2w_gl, dtype=np.float64) @ GL_TO_MITSUBA_CAMERA
        self.sensor_params["to_world"] = self.mi.ScalarTransform4f(to_world.tolist())
        self.sensor_params.update()

    def _render(self, scene, integrator, spp: int, seed: int) -> np.ndarray:
        """Mean of passes of at most :data:`LANES_PER_PASS` samples, each with its own seed."""
        per_pass = max(1, min(spp, LANES_PER_PASS // (self.width * self.height)))
        total, done, k = None, 0, 0
        while done < spp:
            n = min(per_pass, spp - done)
            img = self.mi.render(scene, sensor=self.sensor, integrator=integrator, spp=n,
                                 seed=(seed * 7919 + k) % (1 << 32))
            img = np.array(img, dtype=np.float64) * n
            total = img if total is None else total + img
            done, k = done + n, k + 1
        return (total / spp).astype(np.float32)

    def render_rgba(self, env: str, spp: int, seed: int) -> np.ndarray:
        """``(H, W, 4)``: premultiplied linear RGB of the object and its coverage."""
        return self._render(self.scenes[env], self.path, spp, seed)

    def render_layers(self, env: str, spp: int, seed: int) -> dict[str, np.ndarray]:
        """Specular layer, full radiance and first-hit ground truth (pixel means, background 0)."""
        img = self._render(self.scenes[env], self.layers, spp, seed)
        return {"specular": img[..., :3], "alpha": img[..., 3], "full": img[..., 4:7],
                "albedo": img[..., 7:10], "roughness": img[..., 10], "normal": img[..., 11:14],
                "position": img[..., 14:17]}
