"""benchmarks.heldout: its table reads the runs it finds and states issue 27's targets from the seeds' means."""
import json

import pytest

from benchmarks import heldout


def fake_run(name: str, seed: int, albedo: float, rough: float) -> None:
    run = heldout.run_dir(name, seed)
    (run / "eval").mkdir(parents=True)
    (run / "eval" / "metrics.json").write_text(json.dumps({"masked": {
        "albedo_psnr": albedo, "roughness_mse": rough, "specular_psnr": 20.0, "rgb_psnr": 25.0},
        "whole_image": {"rgb_psnr": 26.0}}))
    (run / "fit_stats.json").write_text(json.dumps({"steps": 3000, "wall_s_this_session": 300.0, "threads": 1,
                                                    "peak_rss_gib": 0.8}))


def test_table_means_the_seeds_and_judges_the_means(tmp_path, monkeypatch):
    monkeypatch.setattr(heldout, "CACHE", tmp_path)
    fake_run("cup@noon", 0, 27.0, 0.010)
    fake_run("cup@noon", 1, 24.0, 0.040)          # mean 25.5 dB, 0.025: both targets missed
    fake_run("bowl@studio", 0, 30.0, 0.008)       # seed 1 not run: the mean is of one seed
    lines = heldout.table(["cup@noon", "bowl@studio", "leaning@overcast"], [0, 1])
    text = "\n".join(lines)
    assert "| cup@noon | 2 | 25.50 | 0.0250 | NOT met | NOT met |" in text
    assert "| bowl@studio | 1 | 30.00 | 0.0080 | met | met |" in text
    assert "leaning@overcast" not in text
    assert sum(ln.startswith("| cup@noon | ") for ln in lines) == 3          # two runs and their mean


def test_scenes_must_name_another_light(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["heldout", "--scenes", "cup"])
    with pytest.raises(SystemExit) as e:
        heldout.main()
    assert e.value.code == 2 and "not OBJECT@ENV" in capsys.readouterr().err
