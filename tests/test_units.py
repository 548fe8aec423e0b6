"""The fit's unit of radiance (:mod:`nefii.fit.units`): colours in the range the fit is made for are taken as they
are; beyond it, a fit of the same scene at another exposure is the same fit, its written light and radiance cache
scaled by the exposure."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from fit_fixtures import write_rendered_scene

from nefii.cli.main import main
from nefii.errors import InputError
from nefii.fit.config import resolve_config
from nefii.fit.outputs import load_run
from nefii.fit.session import prepare_fit
from nefii.fit.units import HIGH, LOW, radiance_unit
from nefii.io.exr import read_exr, write_exr
from nefii.sdf.outputs import load_sdf


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=16, n_train=6, n_test=2)


def exposed(scene: Path, out: Path, k: float) -> Path:
    """A copy of ``scene`` with every training and test image's colour times ``k`` (alpha kept)."""
    shutil.copytree(scene, out)
    for split in ("train", "test"):
        for f in (out / split).glob("r_*.exr"):
            if f.stem.count("_") == 1:                  # r_K.exr, not the ground-truth layers
                img = read_exr(f)
                img[..., :3] *= k
                write_exr(f, img)
    return out


def test_the_unit_is_one_in_range_and_follows_the_images_beyond_it():
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(5000, 3, generator=g) ** 3
    top = float(torch.quantile(rgb.mean(-1), 0.99))
    inside = rgb * (0.5 * (LOW + HIGH) / top)
    assert radiance_unit(inside) == 1.0
    assert radiance_unit(inside * 0.9) == 1.0
    above, below = rgb * (4 * HIGH / top), rgb * (LOW / 4 / top)
    assert radiance_unit(above) == pytest.approx(4.0, rel=1e-5)
    assert radiance_unit(below) == pytest.approx(0.25, rel=1e-5)
    for k in (8.0, 0.125):                                       # exactly: a power of 2
        assert radiance_unit(above * 8.0) == 8.0 * radiance_unit(above)
        assert radiance_unit(below * 0.125) == 0.125 * radiance_unit(below)
    with pytest.raises(InputError, match="black"):
        radiance_unit(torch.zeros(100, 3), Path("somewhere"))


def test_a_fit_does_not_depend_on_the_images_exposure(tiny_scene, tmp_path):
    """The same scene at 8 and at 64 times its exposure (both beyond the range): the same material to the bit, the
    light and the cache 8 times as bright in the second's written model."""
    runs = []
    scenes = (exposed(tiny_scene, tmp_path / "bright", 8.0), exposed(tiny_scene, tmp_path / "brighter", 64.0))
    runs = []
    for data, name in zip(scenes, ("a", "b")):
        run = tmp_path / name
        assert main(["fit", str(data), "--out", str(run), "--preset", "tiny", "--quiet", "--set", "threads=1",
                     "--set", "steps=30"]) == 0
        runs.append(load_run(run))
    a, b = runs
    g = torch.Generator().manual_seed(1)
    x = torch.rand(256, 3, generator=g) - 0.5
    n = torch.nn.functional.normalize(torch.randn(256, 3, generator=g), dim=-1)
    with torch.no_grad():
        ma, mb = a.model.material(x, n), b.model.material(x, n)
        assert torch.equal(ma.albedo, mb.albedo) and torch.equal(ma.roughness, mb.roughness)
        torch.testing.assert_close(b.model.env.radiance(n), 8.0 * a.model.env.radiance(n), rtol=1e-5, atol=0)
        torch.testing.assert_close(b.model.cache(x, n, -n), 8.0 * a.model.cache(x, n, -n), rtol=1e-5, atol=0)


def test_a_checkpoint_in_the_images_units_is_read_into_the_fits(tiny_scene, tmp_path):
    """A checkpoint written before the unit existed holds its model in the images' units: resumed, its light and
    cache are converted to the fit's unit."""
    tiny_scene = exposed(tiny_scene, tmp_path / "dark", 1.0 / 16.0)
    cfg = resolve_config("tiny", [])
    session = prepare_fit(cfg, tiny_scene)
    unit = session.radiance_unit
    assert unit != 1.0
    state = session.trainer.state_dict()
    assert state["radiance_unit"] == unit
    w = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    with torch.no_grad():
        before = session.model.env.radiance(w)
    del state["radiance_unit"]                                   # as an older nefii wrote it
    fresh = prepare_fit(cfg, tiny_scene).trainer
    fresh.load_state_dict(state)
    with torch.no_grad():
        torch.testing.assert_close(fresh.model.env.radiance(w), before / unit, rtol=1e-5, atol=0)
    assert float(fresh.model.cache.radiance_unit) == pytest.approx(1.0 / unit)


def test_a_model_written_before_the_cache_had_a_unit_loads(tiny_scene):
    model = prepare_fit(resolve_config("tiny", []), tiny_scene).model
    state = model.state_dict()
    del state["cache.radiance_unit"]
    model.cache.radiance_unit.fill_(3.0)
    model.load_state_dict(state)
    assert float(model.cache.radiance_unit) == 1.0


def test_the_geometry_stage_does_not_depend_on_the_images_exposure(tiny_scene, tmp_path):
    """`nefii geometry` on the same scene at 8 and at 64 times its exposure (both beyond the range): the same SDF
    to the bit, and the unit it took the colours in recorded (8 times larger for the second); without the unit
    the colour loss's log1p and the colour network's softplus made them two problems."""
    outs = []
    for k, name in ((8.0, "bright"), (64.0, "brighter")):
        scene = exposed(tiny_scene, tmp_path / name, k)
        out = tmp_path / f"geo_{name}"
        assert main(["geometry", str(scene), "--out", str(out), "--preset", "tiny", "--quiet",
                     "--set", "threads=1"]) == 0
        outs.append(out)
    units = [json.loads((o / "geometry_stats.json").read_text())["radiance_unit"] for o in outs]
    assert units[0] > HIGH and units[1] == 8.0 * units[0]
    a, b = (load_sdf(o).sdf.state_dict() for o in outs)
    assert a.keys() == b.keys() and all(torch.equal(a[n], b[n]) for n in a)
