"""Scalars of a run: TensorBoard when the package is installed, and always a CSV beside it."""
from __future__ import annotations

from pathlib import Path

from .config import FitConfig
from .trainer import StepLog


class RunLogger:
    """Writes ``RUN/log.csv`` (step, kind, total, render, cache, background) and TensorBoard scalars."""

    def __init__(self, folder: Path, cfg: FitConfig, every: int = 10) -> None:
        self.every = every
        new = not (folder / "log.csv").exists()
        self._csv = open(folder / "log.csv", "a", buffering=1)
        if new:
            self._csv.write("step,kind,total,render,cache,background\n")
        try:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(folder / "tensorboard"))
        except Exception:  # tensorboard not installed: the CSV still has everything
            self._tb = None

    def __call__(self, rec: StepLog) -> None:
        if rec.step % self.every:
            return
        t = rec.terms
        vals = [t.total.item(), t.render.item(), t.cache.item(), t.background.item()]
        self._csv.write(f"{rec.step},{rec.kind},{vals[0]:.6g},{vals[1]:.6g},{vals[2]:.6g},{vals[3]:.6g}\n")
        if self._tb is not None:
            for name, v in zip(("total", "render", "cache", "background"), vals):
                self._tb.add_scalar(f"{rec.kind}/{name}", v, rec.step)

    def close(self) -> None:
        self._csv.close()
        if self._tb is not None:
            self._tb.close()
