"""End to end: nefii fit and nefii eval on a tiny rendered scene; resume after SIGKILL; bad input."""
import csv
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main
from nefii.evaluate.table1 import METRIC_KEYS
from nefii.errors import InputError
from nefii.fit.config import FitConfig, config_from_dict, config_to_dict, resolve_config, saved_config_from_dict
from nefii.fit.distributed import DistContext, local_device
from nefii.fit.light_init import SUN_START_SHARPNESS, sharpen_lobe
from nefii.fit.losses import SecondaryHitBuffer, SmoothnessPrior, smoothness
from nefii.fit.path_trace import SurfacePoints
from nefii.fit.policies import Alternation, PriorFade, RoughnessWarmup
from nefii.fit.session import prepare_fit


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=16, n_train=6, n_test=2)


def read_log(run: Path) -> list[dict]:
    with open(run / "log.csv") as f:
        return list(csv.DictReader(f))


def test_fit_then_eval_writes_everything_and_the_loss_goes_down(tiny_scene, tmp_path):
    run = tmp_path / "run"
    rc = main(["fit", str(tiny_scene), "--out", str(run), "--preset", "tiny", "--quiet",
               "--set", "steps=80", "--set", "lr=0.02", "--set", "preview_every=40"])
    assert rc == 0
    assert sorted(p.name for p in (run / "previews").iterdir()) == ["step_0000040.png", "step_0000080.png"]
    stats = json.loads((run / "fit_stats.json").read_text())
    assert stats["steps"] == 80 and stats["steps_per_s"] > 0 and stats["peak_rss_gib"] > 0
    for name in ("model.pt", "envmap.exr", "sg.npy", "config.json", "log.csv"):
        assert (run / name).is_file(), name
    sg = np.load(run / "sg.npy")
    assert sg.shape == (16, 7) and np.isfinite(sg).all()
    assert np.allclose(np.linalg.norm(sg[:, :3], axis=-1), 1.0, atol=1e-5)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["steps"] == 80 and cfg["preset"] == "tiny"
    rows = [r for r in read_log(run) if r["kind"] == "observed"]
    early = np.mean([float(r["total"]) for r in rows[:2]])
    late = np.mean([float(r["total"]) for r in rows[-2:]])
    assert late < 0.8 * early, (early, late)

    assert main(["eval", str(run), "--spp", "2", "--quiet"]) == 0
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    for block in ("masked", "whole_image"):
        assert set(metrics[block]) == set(METRIC_KEYS)
        assert metrics[block]["albedo_lpips"] is None
        for k in ("roughness_mse", "albedo_psnr", "rgb_psnr", "specular_psnr"):
            assert isinstance(metrics[block][k], float), (block, k)
    assert len(metrics["views"]) == 2
    for k in (0, 1):
        for kind in ("rgb", "specular", "albedo", "roughness"):
            assert (run / "eval" / f"{k}_{kind}.exr").is_file()
        assert (run / "eval" / f"{k}_grid.png").is_file()
    assert (run / "eval" / "metrics.md").read_text().count("Albedo PSNR") == 2


def _fit_cmd(scene: Path, run: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "nefii.cli.main", "fit", str(scene), "--out", str(run), "--preset", "tiny",
            "--quiet", "--set", "steps=60", "--set", "checkpoint_every_s=0", "--set", "threads=1", *extra]


def test_resume_after_sigkill_matches_an_uninterrupted_run(tiny_scene, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    straight = tmp_path / "straight"
    subprocess.run(_fit_cmd(tiny_scene, straight), check=True, env=env, capture_output=True)

    killed = tmp_path / "killed"
    proc = subprocess.Popen(_fit_cmd(tiny_scene, killed), env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not list((killed / "checkpoints").glob("step_00000[2-4]*.pt")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "model.pt").exists(), "the run finished before it could be killed"
    # a kill during a checkpoint write leaves only a temporary, never a partial step_*.pt
    (killed / "checkpoints" / ".step_0000005.abc.pt").write_bytes(b"partial")
    subprocess.run(_fit_cmd(tiny_scene, killed, "--resume"), check=True, env=env, capture_output=True)
    assert not list((killed / "checkpoints").glob(".*")), "stale temporaries are cleaned on resume"

    a = torch.load(straight / "model.pt", weights_only=True)["state"]
    b = torch.load(killed / "model.pt", weights_only=True)["state"]
    for k in a:
        assert torch.allclose(a[k], b[k], rtol=1e-4, atol=1e-5), k


def test_fit_bad_input_is_one_line_and_exit_2(tiny_scene, tmp_path, capsys):
    assert main(["fit", str(tmp_path / "missing"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing" in err
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "r"), "--set", "no_such_key=1"]) == 2
    assert "no_such_key" in capsys.readouterr().err
    assert main(["fit", str(tiny_scene), "--out", str(tmp_path / "r"), "--mesh", str(tmp_path / "x.ply")]) == 2
    assert "x.ply" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    assert main(["eval", str(tmp_path / "norun")]) == 2
    assert "model.pt" in capsys.readouterr().err


def test_config_round_trips_and_rejects_unknown_fields():
    cfg = resolve_config("paper", ["material.hidden=128", "indirect=off", "tonemap=none"])
    assert cfg.material.hidden == 128 and cfg.material.layers == 8 and cfg.indirect is False
    assert config_from_dict(json.loads(json.dumps(config_to_dict(cfg)))) == cfg
    with pytest.raises(KeyError):
        resolve_config("cpu", ["material.nope=1"])
    with pytest.raises(ValueError):
        resolve_config("cpu", ["indirect=maybe"])
    assert isinstance(resolve_config("cpu", []), FitConfig)


def test_the_brdf_of_each_preset_and_of_runs_saved_before_it_was_a_setting():
    """``cpu`` fits the exact Smith G and Burley's diffuse, ``paper`` the official pair; a config saved
    without ``brdf`` (an older run) reads back as the official pair it was fitted with, one with it as saved."""
    cpu, paper = resolve_config("cpu", []), resolve_config("paper", [])
    assert (cpu.brdf.diffuse, cpu.brdf.shadowing) == ("burley", "smith")
    assert (paper.brdf.diffuse, paper.brdf.shadowing) == ("lambert", "schlick")
    old = config_to_dict(cpu)
    del old["brdf"], old["unobserved_material"]
    assert saved_config_from_dict(old).brdf == paper.brdf
    assert saved_config_from_dict(old).unobserved_material == "all"
    assert saved_config_from_dict(config_to_dict(cpu)) == cpu


def test_eq8_moves_what_of_the_material_it_is_asked_to(tiny_scene):
    """The unobserved step (Eq. 8) trains the cache whatever ``unobserved_material`` says; the material's
    albedo with ``all`` (the official code's neither-side-detached) and ``albedo``, its roughness with
    ``all`` only, neither with ``none`` (the ``cpu`` preset)."""
    assert resolve_config("cpu", []).unobserved_material == "none"
    assert resolve_config("paper", []).unobserved_material == "all"
    for learn in ("all", "albedo", "none"):
        cfg = resolve_config("tiny", [f"unobserved_material={learn}", "unobserved_every=2", "roughness_warmup=0"])
        trainer = prepare_fit(cfg, tiny_scene).trainer
        assert trainer.train_step().kind == "observed"                  # fills the secondary-hit buffer
        model = trainer.model
        last = list(model.material.net.parameters())[-2]                 # output layer's weight: 3 albedo rows, roughness
        assert trainer.train_step().kind == "unobserved"
        assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.cache.parameters())
        grad = last.grad if last.grad is not None else torch.zeros_like(last)
        albedo_rows, roughness_row = grad[:3].abs().sum(), grad[3].abs().sum()
        assert bool(albedo_rows > 0) == (learn != "none"), learn
        assert bool(roughness_row > 0) == (learn == "all"), learn


def test_eq8_trains_only_the_light_lobes_the_cache_can_hold(tiny_scene):
    """With ``unobserved_light = resolvable`` (the ``cpu`` preset) the unobserved step leaves a lobe sharper than
    the cache's direction encoding holds without gradient and trains the others; with ``all`` (``paper``, the
    official code) it trains both. An old run's config reads back as ``all``."""
    assert resolve_config("cpu", []).unobserved_light == "resolvable"
    assert resolve_config("paper", []).unobserved_light == "all"
    old = config_to_dict(resolve_config("cpu", []))
    del old["unobserved_light"]
    assert saved_config_from_dict(old).unobserved_light == "all"
    for learn in ("all", "resolvable"):
        cfg = resolve_config("tiny", [f"unobserved_light={learn}", "unobserved_every=2", "light_solve_every=0"])
        trainer = prepare_fit(cfg, tiny_scene).trainer
        env = trainer.model.env
        limit = trainer.model.cache.max_lobe_sharpness
        with torch.no_grad():                           # half the lobes far sharper than the cache holds
            env.log_sharpness[::2] = math.log(50.0 * limit)
            env.log_sharpness[1::2] = math.log(0.1 * limit)
        assert trainer.train_step().kind == "observed"                  # fills the secondary-hit buffer
        trainer.optimizer.zero_grad()
        assert trainer.train_step().kind == "unobserved"
        grad = env.log_amplitude.grad.abs().sum(-1)
        assert bool(grad[1::2].sum() > 0), learn
        assert bool(grad[::2].sum() > 0) == (learn == "all"), learn


def test_the_searched_sun_is_sharpened_when_the_warm_up_ends_and_survives_a_checkpoint(tiny_scene):
    cfg = resolve_config("tiny", [])
    trainer = prepare_fit(cfg, tiny_scene).trainer
    env, k = trainer.model.env, 5
    sharpen_lobe(env, k, SUN_START_SHARPNESS)
    trainer.sun_lobe = k
    while trainer.step < trainer.warmup.steps:
        trainer.train_step()
    assert float(env().sharpness[k].detach()) < 2 * SUN_START_SHARPNESS     # Adam alone moves it little
    trainer.train_step()
    assert float(env().sharpness[k].detach()) == pytest.approx(cfg.light.sharpness_init_peak, rel=0.01)
    state = trainer.state_dict()
    assert state["sun_lobe"] == k
    fresh = prepare_fit(cfg, tiny_scene).trainer
    fresh.sun_lobe = None
    fresh.load_state_dict(state)
    assert fresh.sun_lobe == k
    del state["sun_lobe"]                                          # a checkpoint from before the search
    fresh.load_state_dict(state)
    assert fresh.sun_lobe is None


def test_the_sky_in_the_sun_lobes_glow_is_left_out_at_its_sharpness_of_the_moment(tiny_scene):
    """Background pixels within the sun lobe's glow are not in the observed batches: while the lobe is wide (the
    warm-up) out to ~25 degrees, and once it is sharpened only within ~9 degrees; without a sun lobe every
    background pixel may be drawn."""
    cfg = resolve_config("tiny", ["background_pixels=512"])
    trainer = prepare_fit(cfg, tiny_scene).trainer
    g = torch.Generator().manual_seed(0)
    d = torch.randn(4096, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    trainer.pixels = dataclasses.replace(trainer.pixels, bg_dirs=d, bg_rgb=torch.full((4096, 3), 0.5),
                                         bg_view=torch.zeros(4096, dtype=torch.long))
    env, k = trainer.model.env, 5
    sharpen_lobe(env, k, SUN_START_SHARPNESS)
    axis = env().axis[k].detach()

    def drawn_within(lo: float, hi: float) -> int:     # over four batches (0-8 degrees: ~10 of 2048 if usable)
        cos = torch.cat([trainer._observed_batch().bg_dirs for _ in range(4)]) @ axis
        return int(((cos <= math.cos(math.radians(lo))) & (cos > math.cos(math.radians(hi)))).sum())
    assert drawn_within(0, 20) > 0                                  # no sun lobe: the whole sky
    trainer.sun_lobe = k
    assert drawn_within(0, 20) == 0 and len(trainer._observed_batch().bg_dirs) > 400
    trainer.step = trainer.warmup.steps                                    # the warm-up's end sharpens it
    trainer.train_step()
    assert float(env().sharpness[k].detach()) == pytest.approx(cfg.light.sharpness_init_peak, rel=0.01)
    axis = env().axis[k].detach()
    counts = [drawn_within(0, 8), drawn_within(10, 20)]
    assert counts[0] == 0 and counts[1] > 0, counts
    trainer.step = 0                                    # a sky seen only within the glow: the solve goes without it
    trainer.pixels = dataclasses.replace(trainer.pixels, bg_dirs=axis.expand(4096, 3).clone())
    trainer.solve_light(0.5)
    assert bool(torch.isfinite(env.log_amplitude).all())


def test_policies():
    w = RoughnessWarmup(steps=5)
    assert [w.override(s) for s in (0, 4, 5, 100)] == [0.5, 0.5, None, None]
    a = Alternation(every=10)
    assert [s for s in range(30) if a.unobserved(s)] == [9, 19, 29]
    assert not any(Alternation(every=10, enabled=False).unobserved(s) for s in range(30))
    f = PriorFade(start=10, end=30, final=0.2)
    assert [f.factor(s) for s in (0, 9, 10, 20, 30, 50)] == pytest.approx([1, 1, 1, 0.6, 0.2, 0.2])
    assert PriorFade(10, 30).factor(25) == 1.0                  # final 1: constant


def test_a_saved_config_without_the_fade_reads_back_as_a_constant_prior():
    from nefii.fit.config import FitConfig, config_to_dict, saved_config_from_dict
    old = config_to_dict(FitConfig())
    del old["smooth_albedo_end"]
    assert saved_config_from_dict(old).smooth_albedo_end == 1.0 and FitConfig().smooth_albedo_end == 0.0


def test_smoothness_prior_compares_neighbours_in_the_tangent_plane():
    """Albedo that changes only across a wall (along z): a prior along the surface z = 0 sees no change,
    and the same prior at points whose normal lies in the plane does."""
    def albedo(x):
        return torch.sigmoid(200.0 * x[..., 2:3]).expand(*x.shape[:-1], 3)

    x = torch.rand(4096, 3) * torch.tensor([1.0, 1.0, 0.0])
    prior = SmoothnessPrior(weight=1.0, radius=0.05)
    up, side = torch.tensor([0.0, 0.0, 1.0]).expand(4096, 3), torch.tensor([1.0, 0.0, 0.0]).expand(4096, 3)

    def prior_at(shading):
        near = prior.neighbours(x, shading, torch.Generator().manual_seed(0))
        torch.testing.assert_close(((near - x) * shading).sum(-1), torch.zeros(4096), atol=1e-6, rtol=0)
        return smoothness(albedo(x), albedo(near), prior.weight).item()

    assert prior_at(up) == 0.0
    assert prior_at(side) > 0.3
    assert smoothness(torch.zeros(5, 3), torch.ones(5, 3), 0.25).item() == 0.25


def test_the_material_is_decoded_along_the_lookup_normal():
    """With a material offset, the material at a surface point is ``M(x + d * lookup_normal)``: changing only
    the lookup normal changes it, changing only the shading normal does not."""
    import trimesh

    from nefii.fit.build import build_model
    from nefii.fit.model import decode_material
    from nefii.raycast import MeshGeometry

    ball = trimesh.creation.icosphere(subdivisions=2)
    geometry = MeshGeometry(ball.vertices, ball.faces)
    box = tuple(torch.from_numpy(b.copy()) for b in geometry.bounds)
    model = build_model(resolve_config("tiny", ["material_offset=0.2"]), box)
    with torch.no_grad():
        for p in model.material.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(2)))
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(256, 3, generator=g), dim=-1)
    tilt = torch.nn.functional.normalize(n + 0.5 * torch.randn(256, 3, generator=g), dim=-1)

    def albedo(normal, lookup):
        pts = SurfacePoints(n.clone(), normal, n.clone(), n.clone(), lookup)
        with torch.no_grad():
            return decode_material(model, pts.position, pts.lookup_normal).albedo

    base = albedo(n, n)
    torch.testing.assert_close(albedo(tilt, n), base)
    assert (albedo(n, tilt) - base).abs().max() > 1e-2
    offset = model.material.normal_offset
    with torch.no_grad():
        direct = torch.sigmoid(model.material.net(model.material.encoding(
            (n + offset * tilt - model.material.box_lo) / model.material.box_size))[..., :3])
    torch.testing.assert_close(albedo(n, tilt), direct)


def test_secondary_buffer_is_a_ring():
    buf = SecondaryHitBuffer(capacity=5)
    mk = lambda a, b: SurfacePoints(*(torch.arange(a, b, dtype=torch.float32).unsqueeze(-1).repeat(1, 3)
                                      for _ in range(5)))
    buf.add(mk(0, 3))
    assert len(buf) == 3
    buf.add(mk(3, 7))  # 7 points into 5 slots: 0 and 1 are overwritten
    assert len(buf) == 5
    vals = set(buf.sample(200, torch.Generator().manual_seed(0)).position[:, 0].tolist())
    assert vals == {2.0, 3.0, 4.0, 5.0, 6.0}


def test_data_parallel_over_two_cpu_processes(tiny_scene, tmp_path):
    run = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           "-m", "nefii.cli.main", "fit", str(tiny_scene), "--out", str(run), "--preset",
                           "tiny", "--quiet", "--device", "cpu", "--set", "threads=1"], env=env, capture_output=True,
                          text=True, timeout=300)
    # the ranks' own output comes first, torchrun's summary of the failure (tracebacks of its own) last
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-1500:]}\nstderr:\n{proc.stderr[:3000]}\n...\n" \
                                 f"{proc.stderr[-800:]}"
    assert "2 processes" in proc.stdout
    assert "the 2 process replicas are in sync" in proc.stdout
    assert (run / "model.pt").is_file() and (run / "sg.npy").is_file()
    # one writer: a single header line in the log
    assert (run / "log.csv").read_text().count("step,kind") == 1


def test_a_non_finite_loss_is_reported_and_never_saved(tiny_scene, tmp_path, monkeypatch, capsys):
    import nefii.fit.trainer as trainer_mod

    real = trainer_mod.observed_loss
    calls = {"n": 0}

    def poisoned(*args, **kwargs):
        terms = real(*args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 4:
            terms = type(terms)(terms.total * float("nan"), terms.render, terms.cache, terms.background)
        return terms

    monkeypatch.setattr(trainer_mod, "observed_loss", poisoned)
    run = tmp_path / "nan"
    rc = main(["fit", str(tiny_scene), "--out", str(run), "--preset", "tiny", "--quiet",
               "--set", "checkpoint_every_s=0"])
    assert rc == 1
    assert "not finite" in capsys.readouterr().out
    assert not (run / "model.pt").exists()
    # the checkpoints are those of the good steps before it
    steps = sorted(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("step_*.pt"))
    assert steps and max(steps) <= 4


def test_more_processes_than_gpus_is_an_input_error(monkeypatch):
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")
    with pytest.raises(InputError, match="2 processes per node but 1 CUDA"):
        local_device(torch.device("cuda"), DistContext(rank=1, world_size=2))
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")  # two nodes of one GPU each
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert local_device(torch.device("cuda"), DistContext(rank=1, world_size=2)) == torch.device("cuda", 0)
    assert local_device(torch.device("cpu"), DistContext(rank=1, world_size=2)) == torch.device("cpu")


def test_the_gpu_preset_on_the_cpu_says_so_and_still_fits(tiny_scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["fit", str(tiny_scene), "--out", str(run), "--preset", "gpu", "--device", "cpu", "--quiet",
                 "--set", "steps=2", "--set", "light_solve_every=0"]) == 0
    assert "the gpu preset on the CPU" in capsys.readouterr().err
    stats = json.loads((run / "fit_stats.json").read_text())
    assert stats["steps"] == 2 and stats["setup_s"] > 0 and "peak_gpu_gib" not in stats
    assert json.loads((run / "config.json").read_text())["batch_pixels"] == 8192
