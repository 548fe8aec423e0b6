"""The one error type users see: bad input, named by file, with exit code 2."""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input. ``str()`` is the one line the CLI prints: ``<path>: <problem>``."""

    exit_code = 2

    def __init__(self, path: str | Path | None, problem: str) -> None:
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
