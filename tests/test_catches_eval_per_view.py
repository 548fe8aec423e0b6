"""``nefii eval`` scores each test view against that view's own ground truth (issue 26, item 7d).

A tiny run is fitted (a few steps: what it predicts does not matter), then evaluated with
``--data`` pointing at a copy of the scene whose ground-truth albedo and roughness are replaced by
hand-made maps that differ from view to view in *pattern* (a constant albedo would be aligned
perfectly by the per-channel median scale whatever the prediction). The per-view numbers in
``RUN/eval/metrics.json`` are recomputed here from the predicted EXRs eval wrote and the maps
written, with numpy alone, and must agree; scoring view 1 against view 0's maps would not.
"""
import json
import math
import shutil

import numpy as np
import pytest
from PIL import Image

from catches_fixtures import fitted_tiny_run
from nefii.cli.main import main
from nefii.io.exr import read_exr, write_exr

RES = 16


def _albedo_truth(view: int) -> np.ndarray:
    """View 0: a ramp along the columns; view 1: a fine checkerboard of two close greys. Different
    spreads, so a view scored against the other's map gets a very different PSNR."""
    r, c = np.mgrid[0:RES, 0:RES].astype(np.float32)
    if view == 0:
        ramp = 0.1 + 0.8 * c / (RES - 1)
        return np.stack([ramp, 0.9 - 0.6 * c / (RES - 1), np.full_like(ramp, 0.4) + 0.2 * r / (RES - 1)], -1)
    check = ((r + c) % 2).astype(np.float32)
    return np.stack([0.30 + 0.05 * check, 0.55 - 0.05 * check, np.full_like(check, 0.2)], -1)


def _roughness_truth(view: int) -> np.ndarray:
    r, c = np.mgrid[0:RES, 0:RES].astype(np.float32)
    return (0.15 + 0.7 * r / (RES - 1)) if view == 0 else np.where((r // 4 + c // 4) % 2 == 0, 0.9, 0.6)


def _srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return -10.0 * math.log10(float(np.mean((a - b) ** 2)))


def _expected(pred_albedo, pred_rough, gt_albedo, gt_rough, mask) -> dict:
    """Table 1's albedo and roughness numbers for one view, both protocols, by hand."""
    scale = np.median(gt_albedo[mask] / np.maximum(pred_albedo[mask], 1e-6), axis=0)
    p, g = _srgb(pred_albedo * scale), _srgb(gt_albedo)
    white = lambda img: np.where(mask[..., None] if img.ndim == 3 else mask, img, 1.0)
    return {"scale": scale,
            "masked": {"albedo_psnr": _psnr(p[mask], g[mask]),
                       "roughness_mse": float(np.mean((pred_rough[mask] - gt_rough[mask]) ** 2))},
            "whole_image": {"albedo_psnr": _psnr(white(p), white(g)),
                            "roughness_mse": float(np.mean((white(pred_rough) - white(gt_rough)) ** 2))}}


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval_per_view")
    scene, run = fitted_tiny_run(root, n_train=2)
    truth = root / "truth"
    shutil.copytree(scene, truth)
    for v in (0, 1):
        write_exr(truth / "test" / f"r_{v}_albedo.exr", _albedo_truth(v))
        write_exr(truth / "test" / f"r_{v}_roughness.exr", _roughness_truth(v))
    assert main(["eval", str(run), "--data", str(truth), "--spp", "1", "--quiet"]) == 0
    return truth, run, json.loads((run / "eval" / "metrics.json").read_text())


def test_eval_scores_each_view_against_its_own_ground_truth(evaluated):
    """(One test on purpose: mutmut credits what the module fixture runs to the first test only.)"""
    truth, run, metrics = evaluated
    assert [v["index"] for v in metrics["views"]] == [0, 1]
    for v, view in enumerate(metrics["views"]):
        mask = np.asarray(Image.open(truth / "test" / f"r_{v}_mask.png").convert("L")) > 127
        assert 20 < mask.sum() < RES * RES
        pred_albedo = read_exr(run / "eval" / f"{v}_albedo.exr").astype(np.float64)
        pred_rough = read_exr(run / "eval" / f"{v}_roughness.exr").astype(np.float64)
        want = _expected(pred_albedo, pred_rough, _albedo_truth(v), _roughness_truth(v), mask)
        assert view["albedo_scale"] == pytest.approx(want["scale"].tolist(), rel=1e-5), v
        for protocol in ("masked", "whole_image"):
            for key in ("albedo_psnr", "roughness_mse"):
                assert view[protocol][key] == pytest.approx(want[protocol][key], rel=1e-4, abs=1e-6), \
                    (v, protocol, key)
        # RGB against the view's own test image, specular against its own map (the fixture's differ per view)
        for key, pred_name, gt_path in (("rgb_psnr", "rgb", truth / "test" / f"r_{v}.exr"),
                                        ("specular_psnr", "specular", truth / "test" / f"r_{v}_specular.exr")):
            pred = _srgb(read_exr(run / "eval" / f"{v}_{pred_name}.exr"))
            gt = _srgb(read_exr(gt_path)[..., :3])
            assert view["masked"][key] == pytest.approx(_psnr(pred[mask], gt[mask]), rel=1e-4), (v, key)
    # the means over views are of these numbers
    for protocol in ("masked", "whole_image"):
        for key in ("albedo_psnr", "roughness_mse"):
            assert metrics[protocol][key] == pytest.approx(
                np.mean([view[protocol][key] for view in metrics["views"]]), rel=1e-9)


def test_the_per_view_truths_are_told_apart(evaluated):
    """The check above is sensitive: view 1 scored against view 0's maps gives other numbers."""
    truth, run, metrics = evaluated
    mask = np.asarray(Image.open(truth / "test" / "r_1_mask.png").convert("L")) > 127
    pred_albedo = read_exr(run / "eval" / "1_albedo.exr").astype(np.float64)
    pred_rough = read_exr(run / "eval" / "1_roughness.exr").astype(np.float64)
    right = _expected(pred_albedo, pred_rough, _albedo_truth(1), _roughness_truth(1), mask)
    wrong = _expected(pred_albedo, pred_rough, _albedo_truth(0), _roughness_truth(0), mask)
    assert abs(right["masked"]["albedo_psnr"] - wrong["masked"]["albedo_psnr"]) > 3.0
    assert abs(right["masked"]["roughness_mse"] - wrong["masked"]["roughness_mse"]) > 0.01
    assert np.abs(right["scale"] - wrong["scale"]).max() > 0.05
