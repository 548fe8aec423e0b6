"""How wrong a fitted light is where the object sees it: fitted SGs against the scene's true environment.

    python -m benchmarks.light_error SCENE_DIR RUN [RUN ...] [--capture CAPTURE_DIR] [--points 2048]

``SCENE_DIR`` holds the truth (``envmap.exr``, ``mesh.ply``, the training views); each ``RUN`` is a fit's
folder (its ``sg.npy``). For each run it prints:

* ``scale``: the fitted light's diffuse irradiance summed over training points, over the true light's (the
  albedo-light scale is not identified; everything below is divided by it);
* the spread of the irradiance error over the points: the standard deviation and the 5% / 95% quantiles of
  ``log(E_fit / scale / E_true)``, ``E`` the irradiance ``sum_d V(x, d) max(n . d, 0) L(d) dOmega`` over a
  lattice of 4096 directions with visibility traced against the mesh. A diffuse point's albedo error is this
  error, so it is the light's share of the albedo error as the object sees it;
* the radiance fitted / true (over the scale) in elevation bands, the cells within 15 degrees of the true
  environment's brightest direction apart (their energy ratio is the last column): where the fitted light put
  energy the truth does not have.

Both lights are binned into the lattice's cells by energy (a 1-degree sun is not point-sampled). With
``--capture`` (the same scene photographed, e.g. ``nefii synth --photo``), it also prints how many of the
capture's background pixels see each band: a direction no background pixel sees is one the background term of
Eq. 7 cannot contradict.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from nefii.data.downscale import training_images
from nefii.data.load import load_scene
from nefii.fit.geometry_source import resolve_source
from nefii.fit.pixels import first_hits, view_rays
from nefii.raycast.base import Geometry, Rays, visible_cosines
from nefii.render.equirect import uv_to_direction
from nefii.render.sg import SGMixture, fibonacci_sphere, sg_eval

from .error_budget import true_environment

BANDS = ((-90, -30), (-30, -10), (-10, 0), (0, 10), (10, 20), (20, 30), (30, 45), (45, 60), (60, 75), (75, 90))
"""elevation bands, degrees (world +Z up)"""
SUN_CONE_DEG = 15.0


@dataclass(frozen=True)
class Lattice:
    """``D`` directions and, for a fine equirectangular grid, each grid pixel's direction, solid angle and
    nearest lattice direction: radiance on the grid binned into the lattice keeps its energy."""

    dirs: Float[Tensor, "D 3"]
    grid: Float[Tensor, "G 3"]
    solid: Float[Tensor, " G"]
    owner: Int[Tensor, " G"]

    @property
    def cell(self) -> float:
        return 4.0 * math.pi / len(self.dirs)

    def binned(self, radiance: Float[Tensor, "G 3"]) -> Float[Tensor, "D 3"]:
        """Each cell's mean radiance: the energy of the grid pixels it owns over its solid angle."""
        energy = torch.zeros(len(self.dirs), 3, dtype=radiance.dtype)
        return energy.index_add_(0, self.owner, radiance * self.solid[:, None]) / self.cell


def lattice(num_directions: int = 4096, grid_height: int = 256, grid_width: int | None = None) -> Lattice:
    """The lattice over an equirectangular grid of ``grid_height`` rows (``grid_width`` columns, default twice
    as many): pass an environment image's own shape to bin it without resampling."""
    dirs = fibonacci_sphere(num_directions)
    H, W = grid_height, grid_width or 2 * grid_height
    v = ((torch.arange(H) + 0.5) / H).unsqueeze(-1).expand(H, W)
    u = ((torch.arange(W) + 0.5) / W).expand(H, W)
    grid = uv_to_direction(u, v).reshape(-1, 3).float()
    solid = (torch.sin(math.pi * v) * (math.pi / H) * (2.0 * math.pi / W)).reshape(-1).float()
    owner = torch.cat([(part @ dirs.T).argmax(-1) for part in grid.split(4096)])
    return Lattice(dirs, grid, solid, owner)


def irradiance_design(position: Float[Tensor, "P 3"], normal: Float[Tensor, "P 3"],
                      geometric_normal: Float[Tensor, "P 3"], geometry: Geometry, dirs: Float[Tensor, "D 3"],
                      cell: float, ray_offset: float) -> Float[Tensor, "P D"]:
    """``V(x_p, d) max(n_p . d, 0) dOmega``: a light's irradiance at the points is this times its radiance."""
    return visible_cosines(position, normal, geometric_normal, geometry, dirs, ray_offset) * cell


@dataclass(frozen=True)
class LightError:
    scale: float
    log_std: float
    log_q05: float
    log_q95: float
    bands: tuple[float, ...]
    """radiance fitted / true over the scale per :data:`BANDS` band, away from the sun (nan: no such cell)"""
    sun: float
    """energy fitted / true over the scale within :data:`SUN_CONE_DEG` of the true brightest direction"""


def light_error(design: Float[Tensor, "P D"], dirs: Float[Tensor, "D 3"], fitted: Float[Tensor, "D 3"],
                true: Float[Tensor, "D 3"]) -> LightError:
    """:class:`LightError` of ``fitted`` against ``true`` (both cell radiances on the lattice ``dirs``)."""
    e_fit, e_true = (design @ fitted).mean(-1), (design @ true).mean(-1)
    scale = float(e_fit.sum() / e_true.sum().clamp_min(1e-30))
    seen = e_true > 1e-6 * e_true.max()
    r = (e_fit[seen] / scale / e_true[seen]).clamp_min(1e-12).log()
    elev = torch.rad2deg(torch.asin(dirs[:, 2].clamp(-1.0, 1.0)))
    lum_fit, lum_true = fitted.mean(-1), true.mean(-1)
    far = dirs @ dirs[lum_true.argmax()] < math.cos(math.radians(SUN_CONE_DEG))
    bands = []
    for lo, hi in BANDS:
        m = (elev >= lo) & (elev < hi) & far
        has = bool(m.any()) and float(lum_true[m].sum()) > 0
        bands.append(float(lum_fit[m].sum() / lum_true[m].sum() / scale) if has else float("nan"))
    sun = float(lum_fit[~far].sum() / lum_true[~far].sum().clamp_min(1e-30) / scale)
    return LightError(scale, float(r.std()), float(r.quantile(0.05)), float(r.quantile(0.95)), tuple(bands), sun)


def refuse(message: str) -> NoReturn:
    """One line on stderr naming the file, exit status 2 (bad input)."""
    print(f"light_error: {message}", file=sys.stderr)
    raise SystemExit(2)


def fitted_light(run: Path) -> SGMixture:
    path = run / "sg.npy"
    if not path.is_file():
        refuse(f"{path}: no such file (is {run} a finished SG fit?)")
    arr = torch.from_numpy(np.load(path)).float()
    return SGMixture(torch.nn.functional.normalize(arr[:, :3], dim=-1), arr[:, 3], arr[:, 4:7])


def background_band_counts(capture: Path, geometry: Geometry, max_side: int = 128) -> list[int]:
    """How many of ``capture``'s training background pixels (rays that miss ``geometry``) see each band."""
    scene, _ = training_images(load_scene(capture, "train"), max_side)
    counts = torch.zeros(len(BANDS), dtype=torch.long)
    for v in range(len(scene)):
        o, d = view_rays(scene, v)
        d = d.reshape(-1, 3)
        miss = ~geometry.intersect(Rays(o.reshape(-1, 3), d)).valid
        elev = torch.rad2deg(torch.asin(d[miss, 2].clamp(-1.0, 1.0)))
        counts += torch.tensor([int(((elev >= lo) & (elev < hi)).sum()) for lo, hi in BANDS])
    return counts.tolist()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, help="the scene with its truth (envmap.exr, mesh.ply)")
    ap.add_argument("runs", type=Path, nargs="+", help="fit folders (sg.npy)")
    ap.add_argument("--capture", type=Path, default=None, help="a photographed capture of the scene")
    ap.add_argument("--points", type=int, default=2048, help="training points the irradiance is compared at")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for f in (args.scene / "envmap.exr", args.scene / "mesh.ply"):
        if not f.is_file():
            refuse(f"{f}: no such file (light_error needs the scene's true environment and mesh)")
    scene = load_scene(args.scene, "train")
    geometry, _ = resolve_source(args.scene / "mesh.ply", None, None, "mesh", args.scene).open()
    pts = first_hits(scene, geometry).points
    pick = torch.randint(len(pts.position), (args.points,), generator=torch.Generator().manual_seed(args.seed))
    pts = pts[pick]
    image = true_environment(args.scene, torch.device("cpu"), height=256).image        # box-filtered, power kept
    lat = lattice(grid_height=image.shape[0], grid_width=image.shape[1])
    design = irradiance_design(pts.position, pts.normal, pts.geometric_normal, geometry, lat.dirs, lat.cell,
                               1e-4 * geometry.scale)
    true = lat.binned(image.reshape(-1, 3).float())
    head = " | ".join(f"{lo}..{hi}" for lo, hi in BANDS)
    print(f"light error against {args.scene / 'envmap.exr'} at {args.points} training points\n")
    print(f"| run | scale | log E std | 5% | 95% | {head} | sun cone |")
    print("|---|" + "---|" * (5 + len(BANDS)))
    for run in args.runs:
        err = light_error(design, lat.dirs, lat.binned(sg_eval(lat.grid, fitted_light(run))), true)
        bands = " | ".join(f"{b:.2f}" for b in err.bands)
        print(f"| {run} | {err.scale:.3f} | {err.log_std:.3f} | {err.log_q05:+.3f} | {err.log_q95:+.3f} | {bands} | "
              f"{err.sun:.2f} |")
    if args.capture is not None:
        counts = background_band_counts(args.capture, geometry)
        print(f"\nbackground pixels of {args.capture} per band: " + ", ".join(
            f"{lo}..{hi}: {n}" for (lo, hi), n in zip(BANDS, counts)))


if __name__ == "__main__":
    main()
