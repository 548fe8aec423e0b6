"""Helpers of the ``test_catches_*`` files: a tiny fitted run (the scene of :mod:`fit_fixtures`)."""
from __future__ import annotations

from pathlib import Path

from fit_fixtures import write_rendered_scene
from nefii.cli.main import main


def fitted_tiny_run(root: Path, steps: int = 4, res: int = 16, n_train: int = 6, n_test: int = 2,
                    overrides: tuple[str, ...] = ()) -> tuple[Path, Path]:
    """``(scene, run)``: :func:`fit_fixtures.write_rendered_scene` in ``root/scene`` and ``nefii fit --preset tiny``
    of it in ``root/run`` (``steps`` steps, ``overrides`` as ``--set`` values)."""
    scene = write_rendered_scene(root / "scene", res=res, n_train=n_train, n_test=n_test)
    run = root / "run"
    sets = [x for kv in (f"steps={steps}", *overrides) for x in ("--set", kv)]
    assert main(["fit", str(scene), "--out", str(run), "--preset", "tiny", "--quiet", *sets]) == 0
    return scene, run
