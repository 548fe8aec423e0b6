"""benchmarks.error_budget's fit rows run at the current trainer (each substitute still fits the model's
interfaces): a few steps of every row on a tiny synthetic scene, scored."""
from __future__ import annotations

import math

import pytest
import torch

from nefii.cli.main import main
from nefii.synth import scenes

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("budget") / "scene"
    assert main(["synth", scenes.smallest_scene(), "--out", str(out), "--res", "24", "--views", "3",
                 "--test-views", "1", "--spp", "2", "--env-height", "32"]) == 0
    return out


@pytest.mark.parametrize("row", ["drift", "roughness_alone", "light_known", "material_known", "indirect_known", "full"])
def test_every_fit_row_runs_and_scores(row, tiny_scene, tmp_path):
    from benchmarks.error_budget import fit_row

    scores = fit_row(tiny_scene, row, 0, tmp_path / row, steps=3, drift_steps=3, eval_spp=1,
                     device=torch.device("cpu"), extra=["batch_pixels=64", "unobserved_points=64",
                                                        "background_pixels=16", "secondary_buffer=4096",
                                                        # the light solve due at every step (the true-light rows
                                                        # must turn it off: it solves SG amplitudes)
                                                        "light_solve_every=1", "light_solve_pixels=64"])
    assert math.isfinite(scores["albedo_psnr"]) and math.isfinite(scores["roughness_mse"])
    if row in ("drift", "roughness_alone"):
        assert math.isfinite(scores["drift_glossy"]) or math.isfinite(scores["drift_rough"])
