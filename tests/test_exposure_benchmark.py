"""benchmarks.exposure: the exposed copy of a scene holds its colour images times the factor and links the rest,
and nefii reads it as the same scene."""
import numpy as np
import pytest
from fit_fixtures import write_rendered_scene

from benchmarks import exposure
from nefii.data import load_scene
from nefii.io.exr import read_exr


def test_an_exposed_scene_scales_colour_and_nothing_else(tmp_path):
    clean = write_rendered_scene(tmp_path / "scene", res=8, n_train=2, n_test=1)
    assert exposure.exposed_scene(clean, 1.0) == clean
    out = exposure.exposed_scene(clean, 8.0)
    assert out.name == "scene_x8" and not any(p.name.startswith(".") for p in tmp_path.iterdir())
    a, b = read_exr(clean / "train" / "r_0.exr"), read_exr(out / "train" / "r_0.exr")
    np.testing.assert_array_equal(b[..., :3], 8.0 * a[..., :3])
    np.testing.assert_array_equal(b[..., 3], a[..., 3])                        # alpha kept
    np.testing.assert_array_equal(read_exr(out / "test" / "r_0_specular.exr"),
                                  8.0 * read_exr(clean / "test" / "r_0_specular.exr"))
    np.testing.assert_array_equal(read_exr(out / "test" / "r_0_albedo.exr"),
                                  read_exr(clean / "test" / "r_0_albedo.exr"))  # a ratio: linked
    assert (out / "test" / "r_0_albedo.exr").is_symlink()
    s0, s1 = load_scene(clean, "train"), load_scene(out, "train")
    assert len(s0) == len(s1) and np.allclose(s1.images.numpy(), 8.0 * s0.images.numpy())
    assert exposure.exposed_scene(clean, 8.0) == out                          # made once


def test_factors_must_be_positive(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["exposure", "--factors", "0"])
    with pytest.raises(SystemExit) as e:
        exposure.main()
    assert e.value.code == 2 and "positive" in capsys.readouterr().err
