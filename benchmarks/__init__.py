"""nefii's benchmarks, run as modules from the repository root: ``python -m benchmarks.fit_speed``,
``python -m benchmarks.quality``, ``python -m benchmarks.geometry``, ``python -m benchmarks.geometry_stability``,
``python -m benchmarks.peers.mitsuba_inverse`` (and ``benchmarks.peers.report``). They use nefii's public API
and its CLI only; results go to ``benchmarks/results/``, scenes and runs to ``benchmarks/.cache/``."""

import nefii  # noqa: E402,F401  (before torch: nefii sets OpenMP's wait policy, see nefii/__init__.py)
