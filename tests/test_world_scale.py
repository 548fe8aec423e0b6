"""A scene's world units are the user's (metres, millimetres, a normalised unit sphere): the same scene with its
cameras and mesh a thousand times larger, or smaller, fits and scores as it does in its own units (ray offsets,
the material field's box and the light are all relative to the geometry)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fit_fixtures import write_rendered_scene

from nefii.cli.main import main


def world_scaled(scene: Path, out: Path, k: float) -> Path:
    """A copy of ``scene`` with every camera position and mesh vertex times ``k``."""
    shutil.copytree(scene, out)
    for split in ("train", "test"):
        path = out / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            m = np.array(frame["transform_matrix"])
            m[:3, 3] *= k
            frame["transform_matrix"] = m.tolist()
        path.write_text(json.dumps(meta))
    mesh = trimesh.load(out / "mesh.ply", force="mesh", process=False)
    trimesh.Trimesh(np.asarray(mesh.vertices) * k, mesh.faces, process=False).export(out / "mesh.ply")
    return out


def fitted_metrics(data: Path, run: Path) -> dict[str, float]:
    assert main(["fit", str(data), "--out", str(run), "--preset", "tiny", "--quiet", "--set", "steps=60",
                 "--set", "threads=1"]) == 0
    assert main(["eval", str(run), "--spp", "4", "--threads", "1", "--quiet"]) == 0
    masked = json.loads((run / "eval" / "metrics.json").read_text())["masked"]
    return {k: v for k, v in masked.items() if v is not None}


def test_a_scene_fits_the_same_in_any_world_units(tmp_path):
    scene = write_rendered_scene(tmp_path / "scene", res=16, n_train=6, n_test=2)
    base = fitted_metrics(scene, tmp_path / "run")
    for k in (1000.0, 0.001):
        other = fitted_metrics(world_scaled(scene, tmp_path / f"scene_{k:g}", k), tmp_path / f"run_{k:g}")
        assert other.keys() == base.keys()
        for name, value in base.items():
            assert other[name] == pytest.approx(value, rel=1e-3, abs=1e-3), (k, name)
