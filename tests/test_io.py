"""Atomic outputs: whole or nothing, usual permissions; EXR round trips; sRGB."""
import os
import stat

import numpy as np
import pytest

from nefii.errors import InputError
from nefii.io.atomic import atomic_dir, atomic_path, write_text_atomic
from nefii.io.exr import read_exr, write_exr
from nefii.io.images import linear_to_srgb, srgb_to_linear


def test_atomic_file_is_whole_or_absent(tmp_path):
    target = tmp_path / "a.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    write_text_atomic(target, "whole")
    assert target.read_text() == "whole"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask


def test_atomic_dir_replaces_as_a_whole(tmp_path):
    target = tmp_path / "out"
    with atomic_dir(target) as d:
        (d / "x").write_text("1")
    with pytest.raises(RuntimeError):
        with atomic_dir(target) as d:
            (d / "y").write_text("2")
            raise RuntimeError("crash")
    assert sorted(p.name for p in target.iterdir()) == ["x"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o777 & ~umask


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3), (5, 7, 4)])
def test_exr_round_trip(tmp_path, shape):
    a = np.random.default_rng(0).uniform(0, 100, shape).astype(np.float32)
    write_exr(tmp_path / "a.exr", a)
    assert np.array_equal(read_exr(tmp_path / "a.exr"), a)
    write_exr(tmp_path / "h.exr", a, half=True)
    assert np.allclose(read_exr(tmp_path / "h.exr"), a, rtol=1e-3)


def test_exr_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_exr(tmp_path / "none.exr")
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(InputError) as e:
        read_exr(bad)
    assert str(bad) in str(e.value)


def test_srgb_round_trip():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    assert np.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)
    assert linear_to_srgb(np.float32(0.0031308)) == pytest.approx(0.04045, abs=1e-5)
