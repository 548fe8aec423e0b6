"""Training-time policies the trainer asks, instead of branches spread through the loop."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RoughnessWarmup:
    """Roughness is held at ``value`` for the first ``steps`` steps (paper: 50 of 120 epochs), then learned."""

    steps: int
    value: float = 0.5

    def override(self, step: int) -> float | None:
        return self.value if step < self.steps else None


@dataclass(frozen=True)
class PriorFade:
    """A prior's weight factor: 1 until step ``start``, then falling linearly to ``final`` at step ``end``."""

    start: int
    end: int
    final: float = 1.0

    def factor(self, step: int) -> float:
        if step < self.start:
            return 1.0
        return 1.0 - (1.0 - self.final) * min(1.0, (step - self.start) / max(self.end - self.start, 1))


@dataclass(frozen=True)
class Alternation:
    """Every ``every``-th step trains on unobserved rays (Eq. 8) instead of observed ones (Eq. 7)."""

    every: int = 10
    enabled: bool = True

    def unobserved(self, step: int) -> bool:
        return self.enabled and self.every > 0 and step % self.every == self.every - 1


@dataclass(frozen=True)
class LightSolveSchedule:
    """The light's amplitudes are solved every ``every`` steps (0: never), not in the last 5% of the ``steps``
    (Adam's restarted moments then settle before the end)."""

    every: int
    steps: int

    def due(self, step: int) -> bool:
        return self.every > 0 and step > 0 and step % self.every == 0 and step < 0.95 * self.steps
