"""Geometry refinement through the estimator: the implicit hit's gradient, and an analytic case (a sphere
that should have a bump, refined under a known light and material) moving toward the truth."""
from __future__ import annotations

import json
import math
import os
import shutil
import socket

import numpy as np
import pytest
import torch
import trimesh
from torch import nn

from fit_fixtures import render, scene_env, scene_material
from nefii.camera import intrinsics_from_fov, look_at, pixel_rays
from nefii.fields.encodings import HashGrid
from nefii.fit.config import FitConfig
from nefii.fit.model import NeFIIModel
from nefii.fit.build import build_model
from nefii.fit.refine import GeometryAnchor, RefineConfig, Refiner, TrainingRays
from nefii.raycast import MeshGeometry, Rays
from nefii.render.brdf import Material
from nefii.sdf.config import resolve_geometry_config
from nefii.sdf.model import NeuSModel
from nefii.sdf.train import ImageObjective
from nefii.sdf.implicit import implicit_hit, newton_along_ray, normal_at
from nefii.sdf.networks import SDFNetwork
from nefii.sdf.normalization import Normalization

BUMP_AXIS = torch.tensor([0.6, 0.0, 0.8])
RADIUS, BUMP, WIDTH = 0.45, 0.1, 0.35


def bumped_sphere() -> trimesh.Trimesh:
    """A sphere of radius 0.45 with a smooth bump of height 0.1 around :data:`BUMP_AXIS`."""
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = np.asarray(m.vertices)
    ang = np.arccos(np.clip(v @ BUMP_AXIS.numpy(), -1, 1))
    r = RADIUS + BUMP * np.exp(-0.5 * (ang / WIDTH) ** 2)
    return trimesh.Trimesh(v * r[:, None], m.faces, process=False)


class TrueMaterial(nn.Module):
    """The fixtures' material as a field: the truth, known to the refinement."""

    def forward(self, position, lookup_normal, roughness_override=None) -> Material:
        return scene_material(position)


def sphere_sdf() -> SDFNetwork:
    torch.manual_seed(0)
    return SDFNetwork(HashGrid(6, 2, 12, 4, 64), 32, 1, 4, init_radius=RADIUS)


def test_implicit_hit_gradient_moves_the_hit_along_the_ray():
    """d x / d theta by the implicit function theorem: for f = |u| - r + b (b the last bias), the hit of a ray
    through the centre moves by -db along the ray's direction's opposite: x = o + (t - b / (n . d)) d."""
    sdf = sphere_sdf()
    o = torch.tensor([[0.0, 0.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    t, res = newton_along_ray(sdf, o, d, torch.tensor([1.4]))
    assert abs(float(t) - (2.0 - RADIUS)) < 1e-4 and float(res) < 1e-5
    x = implicit_hit(sdf, o, d, t)
    assert torch.allclose(x, torch.tensor([[0.0, 0.0, RADIUS]]), atol=1e-4)
    bias = sdf.net[-1].bias
    (g,) = torch.autograd.grad(x[0, 2], bias)
    # raising b by e shrinks the sphere by e: the top hit's z falls by e
    assert abs(float(g[0]) + 1.0) < 1e-3
    n, grad = normal_at(sdf, x)
    assert torch.allclose(n, torch.tensor([[0.0, 0.0, 1.0]]), atol=1e-4) and abs(float(grad.detach().norm()) - 1) < 1e-3


def _views(res: int, n: int):
    K = intrinsics_from_fov(math.radians(40.0), res, res)
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = torch.tensor([2.2 * math.cos(a), 2.2 * math.sin(a), 0.9 + 0.6 * (k % 2)], dtype=torch.float64)
        yield look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)), K


def _rendered_rays(geo: MeshGeometry, res: int, views: int, spp: int) -> TrainingRays:
    """Every pixel of :func:`_views` rendered by the fixtures' estimator under :func:`scene_env`."""
    gen = torch.Generator().manual_seed(0)
    o_all, d_all, rgb_all, mask_all = [], [], [], []
    for c2w, K in _views(res, views):
        rgb, mask, *_ = render(geo, scene_env(), c2w, K, res, gen, spp=spp)
        o, d = pixel_rays(c2w, K, res, res)
        o_all.append(o.reshape(-1, 3).float())
        d_all.append(d.reshape(-1, 3).float())
        rgb_all.append(torch.from_numpy(rgb).reshape(-1, 3))
        mask_all.append(torch.from_numpy(mask).reshape(-1))
    P = sum(len(o) for o in o_all)
    return TrainingRays(torch.cat(o_all), torch.cat(d_all), torch.cat(rgb_all), torch.cat(mask_all),
                        torch.ones(P, dtype=torch.bool))


def _bump_normal_error(sdf: SDFNetwork, truth: MeshGeometry) -> tuple[float, float]:
    """Mean angle (degrees) between the SDF's normal and the truth's over rays that hit the bump, and the
    SDF's value at the bump's true apex."""
    axis = BUMP_AXIS / BUMP_AXIS.norm()
    o = axis * 2.0 + torch.randn(400, 3, generator=torch.Generator().manual_seed(1)) * 0.12
    d = -axis.expand(400, 3)
    hit = truth.intersect(Rays(o.float(), d.float().contiguous()))
    t, _ = newton_along_ray(sdf, o[hit.valid], d[hit.valid], hit.t[hit.valid])
    n, _ = normal_at(sdf, o[hit.valid] + t[:, None] * d[hit.valid])
    cos = (n.detach() * hit.normal[hit.valid]).sum(-1).clamp(-1, 1)
    apex = sdf.sdf(((RADIUS + BUMP) * axis)[None]).detach()
    return float(torch.rad2deg(torch.arccos(cos)).mean()), float(apex)


def test_refinement_grows_the_missing_bump_under_a_known_light():
    """Images of a bumped sphere; the SDF starts as the plain sphere. Material and light are the truth and stay
    fixed (``lr_fields = 0``): only the geometry can explain the bump's shading and silhouette. (Measured on this
    case: 11.9 -> 5.1 degrees and the apex's SDF 0.1 -> 0.001 in 300 steps; the shading term alone takes the
    normals to 7-9 degrees, the normal prior at the preset's 0.05 halves the pace.)"""
    truth = bumped_sphere()
    geo = MeshGeometry(truth.vertices, truth.faces)
    env = scene_env()
    rays = _rendered_rays(geo, res=40, views=10, spp=32)

    fit_cfg = FitConfig(num_samples=4, indirect=False, smooth_albedo=0.0, light_solve_every=0)
    box = (torch.full((3,), -0.6), torch.full((3,), 0.6))
    model = build_model(fit_cfg, box)
    model = NeFIIModel(TrueMaterial(), model.cache, model.env.__class__(num_lobes=3))
    with torch.no_grad():
        model.env.axis_raw.copy_(env.axis)
        model.env.log_sharpness.copy_(env.sharpness.log())
        model.env.log_amplitude.copy_(env.amplitude.log())
    sdf = sphere_sdf()
    before = _bump_normal_error(sdf, geo)
    cfg = RefineConfig(steps=200, batch_pixels=512, lr_fields=0.0, lr_sdf=1.0, remesh_every=50, remesh_resolution=64,
                       silhouette_samples=24, normal_smoothness=0.0)
    refiner = Refiner(cfg, fit_cfg, model, sdf, Normalization((0.0, 0.0, 0.0), 1.0), rays, 0.0, 0.0, (1e-2, 1e-2),
                      torch.device("cpu"))
    for _ in range(cfg.steps):
        refiner.train_step()
    after = _bump_normal_error(sdf, geo)
    # the bump's normals turn toward the truth, and its apex (f = 0.1 on the plain sphere) is reached
    assert before[0] > 8.0, before
    assert after[0] < 0.7 * before[0], (before, after)
    assert abs(after[1]) < 0.5 * abs(before[1]), (before, after)


# --------------------------------------------------------------------------- nefii refine end to end


def test_refine_cli_end_to_end(tmp_path, capsys):
    """fit --geometry GEO, refine, eval: the refined SDF and mesh are written beside the materials, model.pt
    points at them (the fit's own kept), and a second refine or a run without a geometry folder is refused."""
    from fit_fixtures import write_rendered_scene
    from nefii.cli.main import main
    from nefii.fit.outputs import load_run

    scene = write_rendered_scene(tmp_path / "scene", res=20, n_train=6, n_test=1)
    geo, run = tmp_path / "geo", tmp_path / "run"
    assert main(["geometry", str(scene), "--out", str(geo), "--preset", "tiny", "--quiet", "--set", "threads=1",
                 "--from-mesh", str(scene / "mesh.ply"), "--set", "steps=100", "--set", "mesh_resolution=40"]) == 0
    fit = ["fit", str(scene), "--preset", "tiny", "--quiet", "--set", "steps=6", "--set", "threads=1"]
    assert main([*fit, "--out", str(run), "--geometry", str(geo)]) == 0
    refine = ["refine", str(run), "--quiet", "--set", "steps=4", "--set", "batch_pixels=64", "--set", "threads=1",
              "--set", "remesh_resolution=32", "--set", "mesh_resolution=32", "--set", "remesh_every=2"]
    assert main(refine) == 0
    for name in ("sdf.pt", "mesh.ply", "normalization.json", "refine_stats.json"):
        assert (run / "refined" / name).is_file(), name
    assert (run / "model_unrefined.pt").is_file()
    fitted = load_run(run)
    assert fitted.geometry.folder == (run / "refined").resolve()
    assert fitted.mesh == (run / "refined" / "mesh.ply").resolve()
    assert load_run(run).geometry.normal_sigma == json.loads((run / "config.json").read_text())[
        "normal_smoothing_reconstructed"]
    assert main(["eval", str(run), "--spp", "2", "--quiet"]) == 0
    capsys.readouterr()
    assert main(refine) == 2                                        # already refined
    err = capsys.readouterr().err
    assert "already refined" in err and len(err.strip().splitlines()) == 1
    plain = tmp_path / "plain"
    assert main([*fit, "--out", str(plain)]) == 0
    capsys.readouterr()
    assert main(["refine", str(plain), "--quiet"]) == 2             # fitted on a mesh, not a geometry folder
    err = capsys.readouterr().err
    assert "--geometry GEO" in err and len(err.strip().splitlines()) == 1
    assert not (plain / "refined" / "sdf.pt").exists()

def test_refine_keeps_the_geometry_stage_objective(tmp_path, capsys):
    """On a geometry reconstructed from images, refine trains with that stage's objective (its last checkpoint's
    colour network) beside the image term; without that checkpoint it stops with one line naming the folder."""
    from fit_fixtures import write_rendered_scene
    from nefii.cli.main import main

    scene = write_rendered_scene(tmp_path / "scene", res=20, n_train=6, n_test=1)
    geo, run = tmp_path / "geo", tmp_path / "run"
    assert main(["geometry", str(scene), "--out", str(geo), "--preset", "tiny", "--quiet", "--set", "threads=1",
                 "--set", "steps=30", "--set", "mesh_resolution=40", "--set", "batch_rays=64"]) == 0
    assert main(["fit", str(scene), "--preset", "tiny", "--quiet", "--set", "steps=4", "--set", "threads=1",
                 "--out", str(run), "--geometry", str(geo)]) == 0
    shutil.copytree(run, tmp_path / "run2")
    refine = ["--quiet", "--set", "steps=3", "--set", "batch_pixels=64", "--set", "threads=1",
              "--set", "remesh_resolution=32", "--set", "mesh_resolution=32"]
    assert main(["refine", str(run), *refine]) == 0
    stats = json.loads((run / "refined" / "refine_stats.json").read_text())
    assert stats["mean_losses_this_session"]["anchor"] > 0
    assert stats["mean_losses_this_session"]["silhouette"] == 0 == stats["mean_losses_this_session"]["eikonal"]
    # stopped between the phases (the geometry written, the materials' fit not done): --resume runs only the fit
    (run / "refined" / "refine_stats.json").unlink()
    sdf_bytes = (run / "refined" / "sdf.pt").read_bytes()
    capsys.readouterr()
    assert main(["refine", str(run), *refine]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["refine", str(run), *refine, "--resume"]) == 0
    assert (run / "refined" / "sdf.pt").read_bytes() == sdf_bytes
    resumed = json.loads((run / "refined" / "refine_stats.json").read_text())
    assert resumed["steps"] == 3 and resumed["mean_losses_this_session"] == stats["mean_losses_this_session"]
    shutil.rmtree(geo / "checkpoints")
    capsys.readouterr()
    assert main(["refine", str(tmp_path / "run2"), *refine]) == 2
    err = capsys.readouterr().err
    assert "checkpoints" in err and "colour network" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run2" / "refined" / "sdf.pt").exists()
    # a run another live process is writing is left alone
    (tmp_path / "run2" / "run.lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(),
                                                             "verb": "fit", "since": "now"}))
    capsys.readouterr()
    assert main(["refine", str(tmp_path / "run2"), *refine]) == 2
    assert "in use by" in capsys.readouterr().err


@pytest.mark.parametrize("anchored", [False, True])
def test_a_resumed_refinement_continues_the_same_sequence(tmp_path, anchored):
    """Three steps, a checkpoint, three more in a new Refiner, equal to six uninterrupted (mesh included; with the
    geometry stage's objective as an anchor, its colour network too)."""
    from fit_fixtures import scene_mesh

    mesh = scene_mesh()
    rays = _rendered_rays(MeshGeometry(mesh.vertices, mesh.faces), res=16, views=3, spp=4)
    fit_cfg = FitConfig(num_samples=2)
    cfg = RefineConfig(steps=6, batch_pixels=64, remesh_every=2, remesh_resolution=24, silhouette_samples=8)
    box = (torch.full((3,), -0.9), torch.full((3,), 0.9))
    geo_cfg = resolve_geometry_config("tiny", ["batch_rays=32", "samples=8", "importance=8"])

    def refiner() -> Refiner:
        if not anchored:
            return Refiner(cfg, fit_cfg, build_model(fit_cfg, box), sphere_sdf(), Normalization((0.0, 0.0, 0.0), 1.0),
                           rays, 0.005, 0.04, (1e-2, 1e-3), torch.device("cpu"))
        neus = NeuSModel(geo_cfg, background=False)
        anchor = GeometryAnchor(neus, ImageObjective(geo_cfg, rays.origins, rays.directions, rays.rgb, rays.mask),
                                geo_cfg.steps)
        return Refiner(cfg, fit_cfg, build_model(fit_cfg, box), neus.sdf, Normalization((0.0, 0.0, 0.0), 1.0),
                       rays, 0.005, 0.04, (1e-2, 1e-3), torch.device("cpu"), anchor)

    whole = refiner()
    for _ in range(6):
        terms = whole.train_step()
    assert (terms.anchor.item() > 0) == anchored
    first = refiner()
    for _ in range(3):
        first.train_step()
    state = first.state_dict()
    torch.save(state, tmp_path / "c.pt")
    second = refiner()
    second.load_state_dict(torch.load(tmp_path / "c.pt", weights_only=False))
    for _ in range(3):
        second.train_step()
    a, b = whole.state_dict(), second.state_dict()
    assert a["step"] == b["step"] == 6
    parts = ("model", "sdf", "anchor") if anchored else ("model", "sdf")
    for part in parts:
        assert all(torch.equal(a[part][k], b[part][k]) for k in a[part]), part
