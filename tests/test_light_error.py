"""benchmarks/light_error.py: the fitted light against the truth, as the object sees it."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks import light_error as le
from fit_fixtures import scene_env, scene_mesh, write_rendered_scene
from nefii.fit.outputs import sg_array
from nefii.raycast import MeshGeometry
from nefii.render.sg import SGMixture, sg_eval, sg_integral


def test_binning_keeps_energy():
    lat = le.lattice(1024, 64)
    assert torch.allclose(lat.binned(torch.ones(len(lat.grid), 3)).sum(0) * lat.cell,
                          torch.full((3,), 4 * math.pi), rtol=1e-3)
    sg = scene_env()      # a lobe of sharpness 80 keeps its integral through the grid and the cells
    energy = lat.binned(sg_eval(lat.grid, sg)).sum(0) * lat.cell
    assert torch.allclose(energy, (sg.amplitude * sg_integral(sg.sharpness)[:, None]).sum(0), rtol=0.02)


def _design(lat):
    mesh = scene_mesh()
    geometry = MeshGeometry(mesh.vertices, mesh.faces)
    g = torch.Generator().manual_seed(0)
    # points on the ball's upper half and on the slab's top face
    w = torch.nn.functional.normalize(torch.randn(256, 3, generator=g), dim=-1)
    w[:, 2] = w[:, 2].abs()
    ball = (0.45 * w + torch.tensor([0.0, 0.0, 0.05]), w)
    xy = (torch.rand(256, 2, generator=g) - 0.5) * 1.4
    slab = (torch.cat([xy, torch.full((256, 1), -0.4)], -1), torch.tensor([0.0, 0.0, 1.0]).expand(256, 3))
    x, n = (torch.cat([a, b]).float() for a, b in zip(ball, slab))
    return le.irradiance_design(x, n, n, geometry, lat.dirs, lat.cell, 1e-3)


def test_the_true_light_scores_no_error_and_a_moved_sun_does():
    lat = le.lattice(1024, 64)
    design = _design(lat)
    env = scene_env()
    true = lat.binned(sg_eval(lat.grid, env))
    same = le.light_error(design, lat.dirs, 2.0 * true, true)
    assert same.scale == pytest.approx(2.0, rel=1e-5) and same.log_std < 1e-4 and same.sun == pytest.approx(1.0)
    assert all(b == pytest.approx(1.0, rel=1e-4) for b in same.bands if not math.isnan(b))
    moved = SGMixture(torch.tensor([[0.0, 0.0, 1.0], *env.axis[1:].tolist()]), env.sharpness, env.amplitude)
    err = le.light_error(design, lat.dirs, lat.binned(sg_eval(lat.grid, moved)), true)
    assert err.log_std > 0.1                   # the points the sun lit and the ones it now lights disagree
    assert err.bands[-1] > 3.0                 # the zenith holds energy the truth does not
    assert err.sun < 0.5                       # and the sun's cone lost it


def test_cli_prints_a_row_per_run_and_refuses_a_folder_without_sg_in_one_line(tmp_path, capsys):
    data = write_rendered_scene(tmp_path / "s", res=16, n_train=2, n_test=1)
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "sg.npy", sg_array(scene_env()))
    le.main([str(data), str(run), "--points", "64"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith(f"| {run} |"))
    scale, std = (float(x) for x in row.split("|")[2:4])
    assert scale == pytest.approx(1.0, abs=0.05) and std < 0.05      # the truth's own lobes, binned two ways
    with pytest.raises(SystemExit) as exit_:
        le.main([str(data), str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and len(err.splitlines()) == 1 and str(tmp_path / "sg.npy") in err
