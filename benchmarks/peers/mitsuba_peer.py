"""The peer: Mitsuba 3 differentiable path tracing (``prb``) of textures and an env map.

What it optimises, as Mitsuba's inverse-rendering tutorials do (``mi.traverse`` the scene,
``mi.render`` with the parameters, an image loss, ``dr.backward``, Adam, clamp, ``params.update``):

* the ground-truth mesh with the xatlas atlas of ``nefii export`` (:func:`atlas_mesh`);
* its ``principled`` BSDF as nefii's synth renders it (specular 0.5 = F0 0.04, metallic 0):
  ``base_color`` and ``roughness`` bitmaps, bilinear, clamped to [0, 1] and [0.089, 1]
  (nefii's own roughness range) after every step;
* an ``envmap`` emitter, a ``H x 2H`` bitmap on Mitsuba's pole-to-pole grid, optimised as log
  radiance (so a sun can grow by orders of magnitude at Adam's step size) under a total-variation
  prior on that log radiance;
* each step renders ``views_per_step`` random training views at ``spp`` samples with ``prb``
  (emitters hidden from camera rays, as the data was rendered) and compares them with the
  premultiplied RGB of the training EXRs.

Time is measured on the steps only (scene building, the atlas and the curve's evaluations are
outside the clock); each step's parameter update is evaluated before its time is taken.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from nefii.camera import OPENGL_TO_OPENCV
from nefii.data.scene import SceneData
from nefii.export.unwrap import unwrap
from nefii.io.exr import read_exr
from nefii.synth.meshes import TriMesh
from nefii.synth.mitsuba_backend import GL_TO_MITSUBA_CAMERA, build_mesh, envmap_emitter, import_mitsuba, principled

from .hits import TestViews, scatter

ROUGHNESS_MIN = 0.089
"""nefii's roughness floor (``0.911 sigmoid + 0.089``); the peer is held to the same range"""

LOSSES = ("l2", "l1", "l2_log1p")


@dataclass(frozen=True)
class PeerConfig:
    """Everything that decides the peer's fit; saved in its ``result.json``."""

    texture_size: int = 256
    """side of the square base-colour and roughness textures (one xatlas atlas)"""
    env_height: int = 32
    """rows of the env-map bitmap, pole to pole (columns: twice as many)"""
    spp: int = 4
    """samples per pixel of each training render"""
    views_per_step: int = 1
    """training views rendered (and averaged in the loss) per Adam step"""
    max_depth: int = 3
    """prb path length as Mitsuba counts it: 3 = direct light and one indirect bounce"""
    lr_texture: float = 0.02
    """Adam learning rate of both textures"""
    lr_env: float = 0.2
    """Adam learning rate of the env map's log radiance"""
    loss: str = "l2"
    """image loss: ``l2`` (the tutorials' MSE), ``l1``, or ``l2_log1p`` (MSE of log(1 + x))"""
    env_tv: float = 0.01
    """weight of the env map's smoothness prior: mean squared log-radiance difference of neighbours"""
    texture_tv: float = 1.0
    """weight of the textures' smoothness prior: mean squared difference of neighbouring texels"""
    lr_decay: float = 0.1
    """learning rates fall exponentially to this factor at the end of the time budget (nefii: 0.1 over its steps)"""
    albedo_init: float = 0.5
    roughness_init: float = 0.5
    seed: int = 0
    threads: int = 1
    """Dr.Jit worker threads"""

    def validate(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {self.loss!r}")
        if self.texture_size < 8 or self.env_height < 4 or self.spp < 1 or self.views_per_step < 1:
            raise ValueError(f"bad peer config {self}")


# ---------------------------------------------------------------- data

@dataclass(frozen=True)
class CameraRig:
    """A split's cameras as Mitsuba takes them."""

    c2w_gl: np.ndarray
    """(N, 4, 4) camera-to-world, OpenGL axes (what ``MitsubaRenderer.set_camera`` takes)"""
    fov_x_deg: float
    width: int
    height: int


def camera_rig(scene: SceneData) -> CameraRig:
    """``scene``'s cameras (centred pinholes with square pixels and one focal length only)."""
    K = scene.cameras.K.numpy()
    W, H = scene.width, scene.height
    if not (np.allclose(K[:, 0, 0], K[:, 1, 1]) and np.allclose(K[:, 0, 2], 0.5 * W)
            and np.allclose(K[:, 1, 2], 0.5 * H) and np.allclose(K[:, 0, 0], K[0, 0, 0])):
        raise ValueError("the Mitsuba peer needs one centred pinhole with square pixels for every view")
    fov = math.degrees(2.0 * math.atan(0.5 * W / K[0, 0, 0]))
    return CameraRig(scene.cameras.c2w.numpy() @ OPENGL_TO_OPENCV.numpy(), fov, W, H)


def premultiplied_images(scene: SceneData) -> list[np.ndarray]:
    """``(H, W, 3)`` linear RGB per view, the object over black: the RGBA EXRs' premultiplied colour as
    stored (what the renderer wrote), else the loaded straight colour times the mask."""
    out = []
    for v, name in enumerate(scene.names):
        path = scene.root / name
        img = read_exr(path) if path.suffix == ".exr" else None
        if img is not None and img.ndim == 3 and img.shape[-1] == 4:
            out.append(np.ascontiguousarray(img[..., :3], dtype=np.float32))
        else:
            m = np.ones((scene.height, scene.width), bool) if scene.masks is None else scene.masks[v].numpy()
            out.append(scene.images[v].numpy() * m[..., None])
    return out


def atlas_mesh(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, size: int) -> TriMesh:
    """The frozen mesh split at the seams of the xatlas atlas of ``nefii export`` (``nefii.export.unwrap``);
    its triangle ``k`` is ``faces[k]``."""
    a = unwrap(vertices, faces, size)
    return TriMesh(vertices[a.source].astype(np.float64), a.faces, normals[a.source], a.uv)


# ---------------------------------------------------------------- textures

def bitmap_texture(mi, data: np.ndarray) -> dict:
    """A ``bitmap`` texture as nefii synth's scenes have theirs: raw values, bilinear, clamped."""
    img = np.ascontiguousarray(data if data.ndim == 3 else data[..., None], dtype=np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(img), "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}


def texture_at(mi, data: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``data`` ``(S_h, S_w[, 3])`` at texture coordinates ``uv`` ``(M, 2)``, read by Mitsuba's own texture
    lookup (``u`` right, ``v`` down from the top-left, as xatlas and glTF have it)."""
    tex = mi.load_dict(bitmap_texture(mi, data))
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(*np.asarray(uv, np.float32).T)
    return np.array(tex.eval(si) if data.ndim == 3 else tex.eval_1(si), dtype=np.float32).T


def textures_at_hits(mi, views: TestViews, uvs: list[np.ndarray], base_color: np.ndarray, roughness: np.ndarray
                     ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Albedo and roughness images of every test view: the textures at the hits' UVs."""
    return ([scatter(h, texture_at(mi, base_color, uv)) for h, uv in zip(views.hits, uvs)],
            [scatter(h, texture_at(mi, roughness, uv)) for h, uv in zip(views.hits, uvs)])


# ---------------------------------------------------------------- the optimisation

@dataclass
class StepRecord:
    step: int
    fit_s: float
    loss: float


@dataclass
class PeerFit:
    """What the fit leaves: textures, env map (Mitsuba's grid), the loss trace and timings."""

    base_color: np.ndarray
    roughness: np.ndarray
    envmap: np.ndarray
    steps: int
    fit_s: float
    log: list[StepRecord] = field(default_factory=list)


def _sensor(mi, c2w_gl: np.ndarray, fov_x_deg: float, width: int, height: int):
    return mi.load_dict({
        "type": "perspective", "fov": fov_x_deg, "fov_axis": "x", "near_clip": 0.01, "far_clip": 100.0,
        "to_world": mi.ScalarTransform4f((np.asarray(c2w_gl, np.float64) @ GL_TO_MITSUBA_CAMERA).tolist()),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"}})


class MitsubaPeer:
    """Scene, sensors, optimiser; :meth:`fit` runs Adam steps until a time budget is spent."""

    BASE = "object.bsdf.base_color.data"
    ROUGH = "object.bsdf.roughness.data"
    ENV = "env.data"

    def __init__(self, mesh: TriMesh, rig: CameraRig, images: list[np.ndarray], cfg: PeerConfig) -> None:
        cfg.validate()
        mi, dr = import_mitsuba()
        dr.set_thread_count(cfg.threads)
        self.mi, self.dr, self.cfg = mi, dr, cfg
        S, He = cfg.texture_size, cfg.env_height
        We = 2 * He
        env0 = np.full((He, We, 3), self.initial_radiance(images, cfg.albedo_init), np.float32)
        bsdf = mi.load_dict(principled(mi, bitmap_texture(mi, np.full((S, S, 3), cfg.albedo_init, np.float32)),
                                       bitmap_texture(mi, np.full((S, S), cfg.roughness_init, np.float32))))
        obj = build_mesh(mi, mesh.vertices, mesh.faces, mesh.normals, mesh.uv, bsdf)
        self.scene = mi.load_dict({"type": "scene", "object": obj, "env": envmap_emitter(mi, env0)})
        self.sensors = [_sensor(mi, c, rig.fov_x_deg, rig.width, rig.height) for c in rig.c2w_gl]
        self.refs = [mi.TensorXf(img) for img in images]
        self.integrator = mi.load_dict({"type": "prb", "max_depth": cfg.max_depth, "hide_emitters": True})
        self.params = mi.traverse(self.scene)
        # Mitsuba stores the env map with a wrap-around column either side: [W-1, 0 .. W-1, 0]
        cols = np.concatenate([[We - 1], np.arange(We), [0]])
        src = (np.arange(He)[:, None, None] * We + cols[None, :, None]) * 3 + np.arange(3)[None, None, :]
        self._pad_index = mi.UInt32(src.ravel().astype(np.uint32))
        self._pad_shape = (He, We + 2, 3)
        grid = np.arange(He * We * 3).reshape(He, We, 3)
        self._right = mi.UInt32(np.roll(grid, -1, axis=1).ravel().astype(np.uint32))
        self._down = mi.UInt32(grid[1:].ravel().astype(np.uint32))
        self._up = mi.UInt32(grid[:-1].ravel().astype(np.uint32))
        self._tex_pairs = {c: self._neighbour_pairs(mi, S, c) for c in (1, 3)}
        self.opt = mi.ad.Adam(lr=cfg.lr_texture, mask_updates=True)
        self.opt["base"] = self.params[self.BASE]
        self.opt["rough"] = self.params[self.ROUGH]
        self.opt["log_env"] = mi.TensorXf(np.log(env0))
        self.opt.set_learning_rate({"log_env": cfg.lr_env})
        self._apply()
        self.rng = np.random.default_rng(cfg.seed)
        self.step = 0

    @staticmethod
    def _neighbour_pairs(mi, size: int, channels: int):
        """Flat indices of horizontally and vertically adjacent texels of a ``size``-square texture."""
        grid = np.arange(size * size * channels).reshape(size, size, channels)
        pairs = [(grid[:, :-1], grid[:, 1:]), (grid[:-1], grid[1:])]
        return [(mi.UInt32(a.ravel().astype(np.uint32)), mi.UInt32(b.ravel().astype(np.uint32))) for a, b in pairs]

    @staticmethod
    def initial_radiance(images: list[np.ndarray], albedo: float) -> float:
        """A grey constant that makes a white-furnace-lit object of ``albedo`` as bright as the data."""
        total = sum(float(img.sum()) for img in images)
        covered = sum(int((img.sum(-1) > 0).sum()) for img in images)
        return max(total / max(3 * covered, 1) / albedo, 1e-3)

    # ---- parameters
    def _apply(self) -> None:
        """Optimiser state -> scene (the env map through exp and Mitsuba's padding)."""
        mi, dr = self.mi, self.dr
        self.params[self.BASE] = self.opt["base"]
        self.params[self.ROUGH] = self.opt["rough"]
        env = dr.exp(self.opt["log_env"].array)
        self.params[self.ENV] = mi.TensorXf(dr.gather(mi.Float, env, self._pad_index), self._pad_shape)
        self.params.update()

    def _clamp(self) -> None:
        dr = self.dr
        self.opt["base"] = dr.clip(self.opt["base"], 0.0, 1.0)
        self.opt["rough"] = dr.clip(self.opt["rough"], ROUGHNESS_MIN, 1.0)

    # ---- loss
    def _image_loss(self, img, ref):
        dr = self.dr
        if self.cfg.loss == "l1":
            return dr.mean(dr.abs(img - ref), axis=None)
        if self.cfg.loss == "l2_log1p":
            return dr.mean(dr.square(dr.log(1.0 + img) - dr.log(1.0 + ref)), axis=None)
        return dr.mean(dr.square(img - ref), axis=None)

    def _env_prior(self):
        """Mean squared difference of the log radiance of horizontal (wrapping) and vertical neighbours."""
        dr, mi = self.dr, self.mi
        x = self.opt["log_env"].array
        du = dr.gather(mi.Float, x, self._right) - x
        dv = dr.gather(mi.Float, x, self._down) - dr.gather(mi.Float, x, self._up)
        return 0.5 * (dr.mean(dr.square(du), axis=None) + dr.mean(dr.square(dv), axis=None))

    def _texture_prior(self):
        """Mean squared difference of adjacent texels, over both textures (atlas space, seams included)."""
        dr, mi = self.dr, self.mi
        total = 0.0
        for key, c in (("base", 3), ("rough", 1)):
            x = self.opt[key].array
            for a, b in self._tex_pairs[c]:
                total = total + dr.mean(dr.square(dr.gather(mi.Float, x, a) - dr.gather(mi.Float, x, b)), axis=None)
        return total

    def set_progress(self, fraction: float) -> None:
        """Learning rates at ``fraction`` of the budget: ``lr * lr_decay ** fraction``."""
        f = self.cfg.lr_decay ** min(max(fraction, 0.0), 1.0)
        self.opt.set_learning_rate(self.cfg.lr_texture * f)
        self.opt.set_learning_rate({"log_env": self.cfg.lr_env * f})

    def train_step(self) -> float:
        """One Adam step on ``views_per_step`` random training views; returns the image loss."""
        mi, dr, cfg = self.mi, self.dr, self.cfg
        picks = self.rng.choice(len(self.sensors), size=cfg.views_per_step, replace=False)
        loss = 0.0
        for k, v in enumerate(picks):
            img = mi.render(self.scene, self.params, sensor=self.sensors[v], integrator=self.integrator,
                            spp=cfg.spp, seed=int(self.step * cfg.views_per_step + k))
            loss = loss + self._image_loss(img, self.refs[v])
        loss = loss / len(picks)
        total = loss
        if cfg.env_tv > 0:
            total = total + cfg.env_tv * self._env_prior()
        if cfg.texture_tv > 0:
            total = total + cfg.texture_tv * self._texture_prior()
        dr.backward(total)
        self.opt.step()
        self._clamp()
        self._apply()
        value = float(loss.array[0]) if hasattr(loss, "array") else float(loss)
        dr.sync_thread()
        self.step += 1
        return value

    def mean_image_loss(self, spp: int = 16, seed: int = 1 << 20) -> float:
        """The image loss over every training view at a fixed seed, without gradients (for checks)."""
        mi, dr = self.mi, self.dr
        total = 0.0
        with dr.suspend_grad():
            for v, sensor in enumerate(self.sensors):
                img = mi.render(self.scene, sensor=sensor, integrator=self.integrator, spp=spp, seed=seed + v)
                total += float(self._image_loss(img, self.refs[v]).array[0])
        return total / len(self.sensors)

    # ---- results
    def textures(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.array(self.opt["base"], dtype=np.float32),
                np.array(self.opt["rough"], dtype=np.float32)[..., 0])

    def envmap(self) -> np.ndarray:
        """``(H, 2H, 3)`` radiance on Mitsuba's envmap grid (``nefii.synth.mitsuba_backend.mitsuba_grid``)."""
        return np.exp(np.array(self.opt["log_env"], dtype=np.float32))

    def fit(self, budget_s: float, max_steps: int | None = None, on_check: Callable[["MitsubaPeer", float], None]
            | None = None, check_every_s: float = math.inf) -> PeerFit:
        """Steps until ``budget_s`` seconds of stepping (or ``max_steps``); ``on_check(self, fit_s)``
        after the first step and then every ``check_every_s`` fitting seconds, off the clock."""
        fit_s, next_check, log = 0.0, 0.0, []
        while fit_s < budget_s and (max_steps is None or self.step < max_steps):
            t0 = time.perf_counter()
            if max_steps is None:
                self.set_progress(fit_s / budget_s)
            else:
                self.set_progress(self.step / max_steps)
            loss = self.train_step()
            fit_s += time.perf_counter() - t0
            log.append(StepRecord(self.step, fit_s, loss))
            if on_check is not None and fit_s >= next_check:
                on_check(self, fit_s)
                next_check = fit_s + check_every_s
        base, rough = self.textures()
        return PeerFit(base, rough, self.envmap(), self.step, fit_s, log)


def config_record(cfg: PeerConfig) -> dict:
    return {**asdict(cfg), "integrator": "prb", "variant": "llvm_ad_rgb",
            "bsdf": "principled, specular 0.5 (F0 0.04), metallic 0",
            "roughness_range": [ROUGHNESS_MIN, 1.0], "albedo_range": [0.0, 1.0],
            "env_parametrisation": "log radiance, Mitsuba envmap grid (rows pole to pole)",
            "optimizer": "Adam (drjit.opt via mi.ad), mask_updates=True"}
