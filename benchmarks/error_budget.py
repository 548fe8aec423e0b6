"""Where the material error comes from: the ``cpu`` fit with one unknown at a time replaced by the truth.

    python -m benchmarks.error_budget run SCENE_DIR ROW --seed S --out DIR [--steps N] [--eval-spp 32] [--set k=v]
    python -m benchmarks.error_budget adopt RUN SCENE_DIR ROW --seed S --out DIR   # a run made elsewhere as a row
    python -m benchmarks.error_budget table SOURCE...      # -> benchmarks/results/error_budget.md (+ _rows.jsonl)

Rows (each a fit of the ``cpu`` preset, scored by ``nefii.evaluate.run.evaluate_run`` on the test views):

* ``truth_point`` / ``truth_filtered``: no fit. The true material looked up at each test pixel's centre
  (what eval read until 2026-11-25) or averaged over 16 jittered sub-pixel rays (the ground truth's box
  filter, what eval reads now), scored against the ground-truth layers: the ceiling of each protocol;
* ``floor``: no fit. The true material (``material.npz``) under the true environment (``envmap.exr``,
  importance-sampled) with full multi-bounce transport (``nefii.relight``), rendered through nefii's BRDF
  (Lambert + GGX, F0 0.04) and compared with the test photos: what the simplified BRDF costs against the
  renderer's principled BSDF, the best novel-view PSNR any fit could reach;
* ``drift``: everything true (material, environment, indirect light traced with the true material), only
  roughness freed through a zero-initialised residual for ``--drift-steps`` steps, no warm-up: where the
  estimator and the loss pull roughness from the truth;
* ``roughness_alone``: everything true as in ``drift``, but the roughness starts at the warm-up's 0.5
  everywhere and is learned for as many steps as the ``cpu`` fit learns it after its warm-up: whether the
  images determine the roughness when nothing else is unknown (the ``drift`` columns then read fitted - true);
* ``light_known``: the true environment, frozen, in place of the 128 SGs;
* ``material_known``: albedo and roughness frozen at the truth (light and cache are fitted);
* ``albedo_known``: albedo frozen at the truth, roughness, light and cache fitted as ``full`` fits them: set
  beside ``light_known`` and ``roughness_alone``, how much of the roughness error the albedo's freedom costs;
* ``indirect_known``: the radiance cache replaced by tracing further bounces with the current material and
  light (the relight path tracer's transport), to price the cache;
* ``full``: the ``cpu`` preset as ``nefii fit`` runs it;
* ``constant``: albedo 0.5 and roughness 0.5 everywhere, scored without a fit.

A lab script: the substitutes below are benchmark code, built from nefii's public pieces.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from nefii.camera import jittered_pixel_rays, pixel_rays
from nefii.data import load_scene
from nefii.data.material import MaterialOnMesh, load_material
from nefii.evaluate.run import eval_mask, evaluate_run, ground_truth
from nefii.evaluate.table1 import ViewArrays, mean_scores, view_scores
from nefii.fields.cache import RadianceCache
from nefii.fields.encodings import HashGrid
from nefii.fields.mlp import mlp
from nefii.fit.config import resolve_config
from nefii.fit.model import NeFIIModel, decode_material
from nefii.fit.outputs import FittedRun
from nefii.fit.policies import RoughnessWarmup
from nefii.fit.session import prepare_fit
from nefii.fit.trainer import Trainer
from nefii.io.atomic import write_text_atomic
from nefii.raycast import MeshGeometry, Rays
from nefii.relight.environment import load_environment
from nefii.render.envmap import Environment
from nefii.relight.pathtracer import PathSettings, trace_paths
from nefii.relight.render import render_relit
from nefii.render.brdf import ROUGHNESS_MIN, ROUGHNESS_RANGE, BRDFModel, Material, roughness_from_logit
from nefii.render.equirect import pixel_directions

from .common import RESULTS, code_version, machine, stamp, write_results

ROWS = ("truth_point", "truth_filtered", "floor", "drift", "roughness_alone", "light_known", "albedo_known",
        "material_known", "indirect_known", "full", "constant")
GLOSSY = 0.3
"""true roughness below this counts as glossy in the drift figures"""


# --------------------------------------------------------------------------- substitutes for the learned parts

def roughness_logit(r: Tensor) -> Tensor:
    """The inverse of ``roughness_from_logit``."""
    p = ((r - ROUGHNESS_MIN) / ROUGHNESS_RANGE).clamp(1e-4, 1 - 1e-4)
    return torch.log(p) - torch.log1p(-p)


class TrueMaterial(nn.Module):
    """The scene's material with the material field's call signature; ``free_roughness`` adds a learned,
    zero-initialised residual to the roughness logit (the drift row), to that of ``roughness_start`` everywhere
    instead of the truth's if given (the roughness_alone row)."""

    def __init__(self, lookup: MaterialOnMesh, box: tuple[Tensor, Tensor], free_roughness: bool,
                 brdf: BRDFModel, roughness_start: float | None = None) -> None:
        super().__init__()
        self.lookup, self.brdf, self.roughness_start = lookup, brdf, roughness_start
        self.residual = None
        if free_roughness:
            self.encoding = HashGrid(12, 2, 16, 8, 128)
            self.residual = mlp(self.encoding.out_dim, 1, 64, 2)
            with torch.no_grad():
                last = [m for m in self.residual.modules() if isinstance(m, nn.Linear)][-1]
                last.weight.zero_()
                last.bias.zero_()
            self.register_buffer("lo", box[0].float())
            self.register_buffer("size", (box[1] - box[0]).float())

    def forward(self, x: Tensor, normal: Tensor | None = None, roughness_override: float | None = None) -> Material:
        with torch.no_grad():
            m = self.lookup(x.detach(), normal.detach())
        rough = m.roughness.to(x)
        if self.roughness_start is not None:
            rough = torch.full_like(rough, self.roughness_start)
        if self.residual is not None:
            rough = roughness_from_logit(roughness_logit(rough) + self.residual(self.encoding((x - self.lo) / self.size))[..., 0])
        if roughness_override is not None:
            rough = torch.full_like(rough, roughness_override)
        return Material(m.albedo.to(x), rough, self.brdf)


class TrueAlbedo(nn.Module):
    """The fit's own material field with its albedo replaced by the scene's (its roughness is learned)."""

    def __init__(self, field: nn.Module, lookup: MaterialOnMesh) -> None:
        super().__init__()
        self.field, self.lookup = field, lookup

    def forward(self, x: Tensor, normal: Tensor | None = None, roughness_override: float | None = None) -> Material:
        m = self.field(x, normal, roughness_override=roughness_override)
        with torch.no_grad():
            albedo = self.lookup(x.detach(), normal.detach()).albedo.to(x)
        return Material(albedo, m.roughness, m.brdf)


def true_environment(data: Path, device: torch.device, height: int = 256, scale: float = 1.0) -> Environment:
    """The scene's ``envmap.exr`` averaged down to ``height`` rows (power kept; a 1-degree sun stays within a
    pixel or two), so that drawing directions from it costs no more than from the SGs; times ``scale`` (a fit's
    unit of radiance is ``1 / scale`` of the images', :mod:`nefii.fit.units`)."""
    image = load_environment(data / "envmap.exr").image
    f = max(1, image.shape[0] // height)
    H, W = image.shape[0] // f, image.shape[1] // f
    return Environment.from_image(scale * image[:H * f, :W * f].reshape(H, f, W, f, 3).mean((1, 3)).to(device))


class TrueEnvironment(nn.Module):
    """The true environment map, frozen: radiance, and itself as the estimator's light sampler."""

    def __init__(self, env: Environment) -> None:
        super().__init__()
        self.light = env

    def shape_parameters(self) -> list[nn.Parameter]:
        return []

    def radiance(self, w: Tensor) -> Tensor:
        return self.light.radiance(w)

    def scale_radiance(self, k: float) -> None:
        self.light = Environment.from_image(self.light.image * k)

    def light_sampler(self) -> Environment:
        return self.light

    def to_equirect(self, height: int, width: int) -> Tensor:
        return self.radiance(pixel_directions(height, width, device=self.light.image.device))


class PathLight:
    """A learned environment (SG or grid) as the relight path tracer's light: radiance, and directions drawn
    from its estimator sampler with the lobe choice made normal-free (``n = 0``: lobes by energy alone)."""

    def __init__(self, env: nn.Module, generator: torch.Generator | None) -> None:
        self.env, self.sampler, self.generator = env, env.light_sampler(), generator

    def radiance(self, w: Tensor) -> Tensor:
        return self.env.radiance(w).detach()

    def sample_direction(self, u: Tensor) -> Tensor:
        u3 = torch.cat([u, torch.rand(len(u), 1, generator=self.generator, device=u.device, dtype=u.dtype)], -1)
        return self.sampler.sample(torch.zeros_like(u3), u3.unsqueeze(-2))[..., 0, :]

    def pdf_direction(self, w: Tensor) -> Tensor:
        return self.sampler.pdf(torch.zeros_like(w), w.unsqueeze(-2))[..., 0]


class TracedIndirect(nn.Module):
    """The radiance cache's call ``L(x', n', wo)`` answered by path tracing from ``x'`` towards ``wo`` with
    the model's current material and light (no gradient), ``max_bounces`` bounces."""

    def __init__(self, geometry, max_bounces: int = 4, seed: int = 0) -> None:
        super().__init__()
        self.geometry, self.max_bounces, self.seed = geometry, max_bounces, seed
        self.generator: torch.Generator | None = None
        self.model: NeFIIModel | None = None

    def bind(self, model: NeFIIModel) -> None:
        object.__setattr__(self, "model", model)                   # not a submodule: no cycle

    @torch.no_grad()
    def forward(self, position: Tensor, normal: Tensor, wo: Tensor) -> Tensor:
        model = self.model
        if self.generator is None or self.generator.device != position.device:
            self.generator = torch.Generator(device=position.device).manual_seed(self.seed)
        env = model.env.light if isinstance(model.env, TrueEnvironment) else PathLight(model.env, self.generator)
        eps = 1e-3 * self.geometry.scale
        rays = Rays(position + eps * wo, -wo)
        out = trace_paths(rays, self.geometry, lambda x, nl: decode_material(model, x, nl), env, self.generator,
                          PathSettings(max_bounces=self.max_bounces))
        return out.radiance.to(position)


# --------------------------------------------------------------------------- rows

def constant_scores(scene) -> dict:
    views = []
    for v in range(len(scene)):
        truth = ground_truth(scene, v)
        mask = eval_mask(scene, v, np.ones(truth.rgb.shape[:2], bool))
        pred = ViewArrays(truth.rgb, np.full_like(truth.albedo, 0.5), np.full_like(truth.roughness, 0.5), None)
        views.append(view_scores(pred, truth, mask)[0])
    return mean_scores(views)["masked"]


def true_scene(data: Path):
    """The test split, its mesh and the true material on it."""
    scene = load_scene(data, "test")
    mesh = MeshGeometry.from_file(scene.mesh_path)
    return scene, mesh, MaterialOnMesh(load_material(data), mesh)


@torch.no_grad()
def truth_scores(data: Path, subpixels: int, seed: int) -> dict:
    """The true material at the test views, point-sampled (``subpixels`` 1) or box-filtered."""
    scene, mesh, truth_material = true_scene(data)
    H, W = scene.height, scene.width
    g = torch.Generator().manual_seed(seed)
    views = []
    for v in range(len(scene)):
        pix = torch.arange(H * W).repeat_interleave(subpixels)
        u = torch.full((len(pix), 2), 0.5, dtype=torch.float64) if subpixels == 1 else \
            torch.rand(len(pix), 2, generator=g, dtype=torch.float64)
        o, d = jittered_pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], W, pix, u)
        hit = mesh.intersect(Rays(o.float(), d.float()))
        m = truth_material(hit.position[hit.valid], hit.normal[hit.valid])
        p = pix[hit.valid]
        n = torch.zeros(H * W).index_add_(0, p, torch.ones(len(p))).clamp_min(1)
        albedo = torch.zeros(H * W, 3).index_add_(0, p, m.albedo) / n.unsqueeze(-1)
        rough = torch.zeros(H * W).index_add_(0, p, m.roughness) / n
        truth = ground_truth(scene, v)
        mask = eval_mask(scene, v, (n > 0).reshape(H, W).numpy())
        pred = ViewArrays(truth.rgb, albedo.reshape(H, W, 3).numpy(), rough.reshape(H, W).numpy(), None)
        views.append(view_scores(pred, truth, mask)[0])
    return mean_scores(views)["masked"]


@torch.no_grad()
def floor_scores(data: Path, spp: int, seed: int) -> dict:
    scene, mesh, truth_material = true_scene(data)
    env = load_environment(data / "envmap.exr")
    g = torch.Generator().manual_seed(seed)
    views = []
    for v in range(len(scene)):
        img = render_relit(mesh, truth_material, env, scene.cameras.c2w[v], scene.cameras.K[v], scene.height,
                           scene.width, spp, g, PathSettings(max_bounces=8))
        truth = ground_truth(scene, v)
        mask = eval_mask(scene, v, img.coverage.numpy() > 0)
        views.append(view_scores(ViewArrays(img.rgb.numpy(), None, None, None), truth, mask)[0])
    return mean_scores(views)["masked"]


def fit_row(data: Path, row: str, seed: int, out: Path, steps: int | None, drift_steps: int, eval_spp: int,
            device: torch.device, extra: list[str] = ()) -> dict:
    overrides = [f"seed={seed}", "preview_every=0", "checkpoint_every_s=1e9", *extra]
    if steps is not None:
        overrides.append(f"steps={steps}")
    if row in ("drift", "roughness_alone", "material_known"):
        overrides.append("roughness_warmup=0")                      # the truth needs no warm-up
    if row == "drift":
        overrides.append(f"steps={drift_steps}")
    if row == "roughness_alone":
        preset = resolve_config("cpu", [f"steps={steps}"] if steps is not None else [])
        overrides.append(f"steps={round(preset.steps * (1 - preset.roughness_warmup))}")
    if row in ("drift", "roughness_alone", "indirect_known"):
        overrides.append("unobserved=false")                        # no cache to keep consistent
    if row in ("drift", "roughness_alone", "light_known"):
        overrides += ["light_prior=0", "light_solve_every=0"]     # a prior on, or a solve of, a light not fitted
    cfg = resolve_config("cpu", overrides)
    session = prepare_fit(cfg, data, device=device)
    cfg, model, geometry = session.config, session.model, session.geometry
    if row in ("drift", "roughness_alone", "material_known"):
        model.material = TrueMaterial(MaterialOnMesh(load_material(data), geometry), session.box,
                                      row != "material_known", cfg.brdf,
                                      RoughnessWarmup(0).value if row == "roughness_alone" else None)
    if row == "albedo_known":
        model.material = TrueAlbedo(model.material, MaterialOnMesh(load_material(data), geometry))
    unit = session.radiance_unit
    if row in ("drift", "roughness_alone", "light_known"):
        model.env = TrueEnvironment(true_environment(data, device, scale=1.0 / unit))
    if row in ("drift", "roughness_alone", "indirect_known"):
        model.cache = TracedIndirect(geometry, seed=seed)
        model.cache.bind(model)
    trainer = Trainer(cfg, model, geometry, session.pixels, device, sun_lobe=session.trainer.sun_lobe)
    t0 = time.time()
    while trainer.step < cfg.steps:
        trainer.train_step()
    fit_s = time.time() - t0
    model.eval()
    model.env.scale_radiance(unit)                                  # back in the images' units, as nefii fit writes
    if isinstance(model.cache, RadianceCache):                      # (traced indirect light follows the env)
        model.cache.radiance_unit.mul_(unit)
    fitted = FittedRun(out, cfg, model, data, session.source.mesh, session.source, session.box)
    test = load_scene(data, "test")
    means = evaluate_run(fitted, test, out / "eval", eval_spp, 0)["masked"]
    means["fit_s"] = fit_s
    if row in ("drift", "roughness_alone"):
        means.update(drift_figures(model, test, geometry))
    return means


@torch.no_grad()
def drift_figures(model: NeFIIModel, scene, geometry) -> dict:
    """Mean of (fitted - true) roughness over glossy and over rough pixels of the test views."""
    d_glossy, d_rough = [], []
    for v in range(len(scene)):
        o, d = pixel_rays(scene.cameras.c2w[v], scene.cameras.K[v], scene.height, scene.width)
        hit = geometry.intersect(Rays(o.reshape(-1, 3).float(), d.reshape(-1, 3).float()))
        gt = scene.ground_truth.roughness[v].reshape(-1)
        mask = hit.valid & scene.ground_truth.mask[v].reshape(-1)
        dev = next(model.parameters()).device
        pred = decode_material(model, hit.position[mask].to(dev), hit.lookup_normal[mask].to(dev)).roughness.cpu()
        diff = pred - gt[mask]
        glossy = gt[mask] < GLOSSY
        d_glossy.append(diff[glossy])
        d_rough.append(diff[~glossy])
    return {"drift_glossy": float(torch.cat(d_glossy).mean()), "drift_rough": float(torch.cat(d_rough).mean())}


# --------------------------------------------------------------------------- table

ROWS_FILE = "error_budget_rows.jsonl"
"""every row's scores.json the table was made from, one JSON object a line, kept beside it in results/: the runs
themselves live in a cache that does not last, and a later session adds its rows (a second seed, say) to these"""


def read_rows(sources: list[Path]) -> list[dict]:
    """The rows' scores: each source a runs folder (``<scene>/<row>_s<seed>/scores.json``) or a rows file; a later
    source's (scene, row, seed) replaces an earlier one's."""
    rows: dict[tuple[str, str, int], dict] = {}
    for src in sources:
        blobs = ([json.loads(line) for line in src.read_text().splitlines() if line.strip()] if src.is_file()
                 else [json.loads(f.read_text()) for f in sorted(src.glob("*/*/scores.json"))])
        rows.update({(b["scene"], b["row"], b["seed"]): b for b in blobs})
    return [rows[k] for k in sorted(rows)]


def table(sources: list[Path], where: str, code: str | None = None) -> None:
    rows = read_rows(sources)
    found: dict[tuple[str, str], list[dict]] = {}
    for blob in rows:
        found.setdefault((blob["scene"], blob["row"]), []).append(blob)
    scenes = sorted({s for s, _ in found})

    def cell(vals: list[float | None], fmt: str) -> str:
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        if not vals:
            return "-"
        m = float(np.mean(vals))
        return (fmt.format(m) + (f" ± {fmt.replace('+', '').format(np.ptp(vals) / 2)}" if len(vals) > 1 else "")) + \
            ("" if len(vals) > 1 else " (1 seed)")

    lines = [f"# error_budget ({stamp()}, runs at code {code or code_version()})", "", f"Table written on: {machine()}. "
             f"Runs: {where or 'here'}.", "",
             "The `cpu` preset on ground-truth geometry with one unknown replaced by the truth at a time "
             "(benchmarks/error_budget.py). Mean of the seeds ± half their spread; masked test views. "
             "Albedo aligned per view and channel as eval does, each pixel's material averaged over its sub-pixel "
             "rays as the ground truth's layers are (`truth_filtered` is that protocol's ceiling, `truth_point` "
             "the material read at pixel centres).", ""]
    for scene in scenes:
        lines += [f"## {scene}", "", "| row | albedo PSNR | roughness MSE | specular PSNR | RGB PSNR | drift glossy "
                  "| drift rough | seeds |", "|---|---|---|---|---|---|---|---|"]
        for row in ROWS:
            blobs = found.get((scene, row), [])
            if not blobs:
                continue
            get = lambda k: [b["scores"].get(k) for b in blobs]  # noqa: E731
            lines.append(f"| {row} | {cell(get('albedo_psnr'), '{:.2f}')} | {cell(get('roughness_mse'), '{:.4f}')} "
                         f"| {cell(get('specular_psnr'), '{:.2f}')} | {cell(get('rgb_psnr'), '{:.2f}')} "
                         f"| {cell(get('drift_glossy'), '{:+.3f}')} | {cell(get('drift_rough'), '{:+.3f}')} "
                         f"| {', '.join(str(b['seed']) for b in blobs)} |")
        lines.append("")
    write_results("error_budget.md", lines)
    write_text_atomic(RESULTS / ROWS_FILE, "".join(json.dumps(b, sort_keys=True) + "\n" for b in rows))


def row_folder(root: Path, data: Path, row: str, seed: int) -> Path:
    """``root/<scene>/<row>_s<seed>``, made if missing: where a row's run and its ``scores.json`` live."""
    out = root / data.name / f"{row}_s{seed}"
    out.mkdir(parents=True, exist_ok=True)
    return out


def save_row(out: Path, data: Path, row: str, seed: int, scores: dict, **extra) -> None:
    """A row's ``scores.json`` (what :func:`table` reads), written atomically, and printed."""
    blob = {"scene": data.name, "row": row, "seed": seed, "scores": scores, **extra}
    write_text_atomic(out / "scores.json", json.dumps(blob, indent=2) + "\n")
    print(json.dumps(blob))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("data", type=Path)
    r.add_argument("row", choices=ROWS)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--steps", type=int, default=None, help="override the preset's steps (smoke tests)")
    r.add_argument("--drift-steps", type=int, default=300)
    r.add_argument("--eval-spp", type=int, default=32)
    r.add_argument("--threads", type=int, default=2)
    r.add_argument("--device", default="cpu")
    r.add_argument("--set", dest="overrides", action="append", default=[],
                   help="config override for the fit rows, e.g. brdf.shadowing=schlick (the true material reads it too)")
    a = sub.add_parser("adopt", help="record a finished `nefii fit` + `nefii eval` run (benchmarks.quality's `full`, "
                                     "say) as a row, its masked figures read from RUN/eval/metrics.json")
    a.add_argument("run", type=Path)
    a.add_argument("data", type=Path)
    a.add_argument("row", choices=ROWS)
    a.add_argument("--seed", type=int, required=True)
    a.add_argument("--out", type=Path, required=True)
    t = sub.add_parser("table")
    t.add_argument("runs", type=Path, nargs="+",
                   help="runs folders and rows files (results/error_budget_rows.jsonl); later ones win")
    t.add_argument("--where", default="", help="where and how the runs ran, for the record")
    t.add_argument("--code", default=None, help="the commit the runs were made at (default: the current one)")
    args = ap.parse_args()
    if args.cmd == "table":
        table(args.runs, args.where, args.code)
        return
    if args.cmd == "adopt":
        metrics = json.loads((args.run / "eval" / "metrics.json").read_text())["masked"]
        save_row(row_folder(args.out, args.data, args.row, args.seed), args.data, args.row, args.seed, metrics,
                 source=str(args.run))
        return
    torch.set_num_threads(args.threads)
    out = row_folder(args.out, args.data, args.row, args.seed)
    t0 = time.time()
    if args.row == "constant":
        scores = constant_scores(load_scene(args.data, "test"))
    elif args.row in ("truth_point", "truth_filtered"):
        scores = truth_scores(args.data, 1 if args.row == "truth_point" else 16, args.seed)
    elif args.row == "floor":
        scores = floor_scores(args.data, spp=64, seed=args.seed)
    else:
        scores = fit_row(args.data, args.row, args.seed, out, args.steps, args.drift_steps, args.eval_spp,
                         torch.device(args.device), args.overrides)
    save_row(out, args.data, args.row, args.seed, scores, wall_s=time.time() - t0)


if __name__ == "__main__":
    main()
