"""nefii: NeFII inverse rendering (materials, SG lighting and a neural radiance cache from multi-view images).

Importing nefii before torch makes OpenMP threads that wait at a barrier sleep instead of spinning
(``OMP_WAIT_POLICY=PASSIVE``, unless the environment already sets it): with libgomp's spinning default, a fit
beside one other busy process ran at 26% of its alone rate and beside a two-thread PyTorch process at 10%;
passive, at 79% and 93%, for about a quarter of the alone rate (11.0 -> 8.1 steps/s; benchmarks/results/
contention.md, docs/experiments.md 2026-11-26). libgomp reads the variable once, when torch loads it.
"""
import os as _os

_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
