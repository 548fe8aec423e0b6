"""Run folders are untrusted input and protect themselves (docs/reliability.md): a crafted pickle in any
``.pt`` nefii reads runs nothing on any entry point; resume falls back past a corrupt newest checkpoint and
refuses other data; a second writer is refused; a failed run can be rerun or resumed; a foreign folder is
left alone."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from fit_fixtures import write_rendered_scene
from nefii.io.checkpoints import list_checkpoints
from nefii.io.lock import LOCK_FILE
from test_bad_input import assert_one_line_error, cli, run, scene  # noqa: F401 (fixtures: a tiny scene, a finished tiny fit)
from test_checkpoints import Payload

TINY = ["--preset", "tiny", "--quiet", "--set", "threads=1"]


# ---------------------------------------------------------------------------- crafted pickles

def _run_copy(run: Path, tmp: Path) -> Path:
    return Path(shutil.copytree(run, tmp / "run"))


def _poison(path: Path, marker: Path) -> None:
    torch.save({"step": 10**6, "config": Payload(marker), "state": {}}, path)


def _geometry_run(tmp: Path, marker: Path) -> Path:
    geo = tmp / "geo"
    (geo / "checkpoints").mkdir(parents=True)
    (geo / "run.json").write_text(json.dumps({"kind": "geometry", "data": None}))
    _poison(geo / "checkpoints" / "step_0000010.pt", marker)
    return geo


def _sdf_folder(scene: Path, tmp: Path, marker: Path) -> Path:
    geo = tmp / "geo"
    geo.mkdir()
    shutil.copy(scene / "mesh.ply", geo / "mesh.ply")
    _poison(geo / "sdf.pt", marker)
    return geo


ENTRY_POINTS = ["eval", "export", "relight", "view", "fit --resume", "fit --geometry sdf", "geometry --resume"]


@pytest.mark.parametrize("entry", ENTRY_POINTS)
def test_a_crafted_pickle_runs_nothing_and_is_refused(entry, scene, run, tmp_path):
    marker = tmp_path / "MARKER"
    if entry in ("eval", "export", "relight", "view"):
        target = _run_copy(run, tmp_path)
        poisoned = target / "model.pt"
        _poison(poisoned, marker)
        extra = {"eval": ["--spp", "1"], "export": ["--texture-size", "16"], "view": ["--texture-size", "16"],
                 "relight": ["--envmap", scene / "envmap.exr", "--spp", "1"]}[entry]
        argv = [entry, target, *extra, "--quiet"]
    elif entry == "fit --resume":
        target = _run_copy(run, tmp_path)
        poisoned = list_checkpoints(target / "checkpoints")[-1]
        _poison(poisoned, marker)
        argv = ["fit", scene, "--out", target, *TINY, "--resume"]
    elif entry == "fit --geometry sdf":
        geo = _sdf_folder(scene, tmp_path, marker)
        poisoned = geo / "sdf.pt"
        argv = ["fit", scene, "--out", tmp_path / "out", *TINY, "--geometry", geo, "--set", "geometry_mode=sdf"]
    else:
        geo = _geometry_run(tmp_path, marker)
        poisoned = geo / "checkpoints" / "step_0000010.pt"
        argv = ["geometry", scene, "--out", geo, "--preset", "tiny", "--quiet", "--resume"]
    r = cli(argv)
    assert_one_line_error(r, str(poisoned), "refused", "could run code")
    assert not marker.exists(), "the pickle's payload ran"


# ---------------------------------------------------------------------------- resume

def test_resume_falls_back_past_a_truncated_newest_checkpoint_and_says_which(scene, run, tmp_path):
    target = _run_copy(run, tmp_path)
    older, newest = list_checkpoints(target / "checkpoints")[-2:]
    newest.write_bytes(newest.read_bytes()[:200])
    r = cli(["fit", scene, "--out", target, *TINY, "--resume"])
    assert r.rc == 0, r.err
    assert any(newest.name in w and "skipping" in w for w in r.warnings), r.err
    assert f"resumed from {older}" in r.out


def test_resume_on_other_data_is_refused(scene, run, tmp_path):
    other = write_rendered_scene(tmp_path / "other", res=16, n_train=6, n_test=2, seed=1)
    target = _run_copy(run, tmp_path)
    before = (target / "model.pt").read_bytes()
    r = cli(["fit", other, "--out", target, *TINY, "--resume"])
    assert_one_line_error(r, "--resume on other data", "images differ")
    assert (target / "model.pt").read_bytes() == before


def test_a_second_writer_is_refused_naming_the_holder(scene, tmp_path):
    out = tmp_path / "run"
    holder = subprocess.Popen(["sleep", "60"])
    try:
        out.mkdir()
        (out / LOCK_FILE).write_text(json.dumps({"pid": holder.pid, "host": os.uname().nodename, "verb": "fit",
                                                 "since": "2026-11-25 10:00:00"}))
        r = cli(["fit", scene, "--out", out, *TINY])
        assert_one_line_error(r, f"pid {holder.pid}", "nefii fit", "in use by")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_FILE], "the second writer wrote nothing"
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: its lock is stale, taken over with a warning, and released at the end
    r = cli(["fit", scene, "--out", out, *TINY, "--set", "steps=2"])
    assert r.rc == 0, r.err
    assert any("no longer running" in w for w in r.warnings), r.err
    assert not (out / LOCK_FILE).exists()


def _poison_the_loss(monkeypatch):
    import nefii.fit.trainer as trainer_mod
    real = trainer_mod.observed_loss

    def poisoned(*args, **kwargs):
        terms = real(*args, **kwargs)
        return type(terms)(terms.total * float("nan"), terms.render, terms.cache, terms.background)

    monkeypatch.setattr(trainer_mod, "observed_loss", poisoned)


@pytest.mark.parametrize("again", ["rerun", "resume"])
def test_a_failed_run_can_be_rerun_or_resumed(scene, tmp_path, monkeypatch, again):
    out = tmp_path / "run"
    with monkeypatch.context() as m:
        _poison_the_loss(m)
        r = cli(["fit", scene, "--out", out, *TINY])                    # checkpoints every 60 s: none written
    assert r.rc == 1 and "no checkpoint was written" in r.out and "last good checkpoint" not in r.out
    assert not list_checkpoints(out / "checkpoints")
    r = cli(["fit", scene, "--out", out, *TINY, "--set", "steps=3", *(["--resume"] if again == "resume" else [])])
    assert r.rc == 0, r.err
    assert (out / "model.pt").is_file() and not (out / LOCK_FILE).exists()
    if again == "resume":
        assert "starting from the first step" in r.out


def test_a_foreign_folder_is_left_alone(scene, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "config.json").write_text("{}")
    r = cli(["fit", scene, "--out", mine, *TINY])
    assert_one_line_error(r, "neither empty nor a nefii fit run")
    assert sorted(p.name for p in mine.iterdir()) == ["config.json"]
    r = cli(["geometry", scene, "--out", mine, "--preset", "tiny", "--quiet"])
    assert_one_line_error(r, "neither empty nor a nefii geometry run")


def test_a_finished_run_is_not_overwritten_without_resume(scene, run):
    r = cli(["fit", scene, "--out", run, *TINY])
    assert_one_line_error(r, "already holds a run", "--resume")


def test_geometry_resume_on_other_data_is_refused(scene, tmp_path):
    geo = tmp_path / "geo"
    r = cli(["geometry", scene, "--out", geo, "--preset", "tiny", "--quiet", "--set", "steps=2", "--set", "threads=1"])
    assert r.rc == 0, r.err
    assert json.loads((geo / "run.json").read_text())["kind"] == "geometry"
    other = write_rendered_scene(tmp_path / "other", res=16, n_train=6, n_test=2, seed=1)
    r = cli(["geometry", other, "--out", geo, "--preset", "tiny", "--quiet", "--resume"])
    assert_one_line_error(r, "--resume on other data", "images differ")
    r = cli(["fit", scene, "--out", geo, *TINY])
    assert_one_line_error(r, "holds a nefii geometry run, not a fit run")
