"""The views an interrupted ``nefii eval`` or ``nefii relight`` already rendered, kept so that a rerun goes on
from them.

An eval of a large test set runs for hours on a CPU (200 views at 512 x 512 take about a minute each on two
cores), a relight longer. Each finished view is committed to a hidden folder beside the output's (``RUN/eval``
-> ``RUN/.eval.partial``): its files first, then ``K.json`` (its record, e.g. its entry of ``metrics.json``) as
the commit mark. A rerun with the same key (the folder's ``key.json``: model, data and settings) renders only
the views without a mark; any other key clears the folder. Every view renders from its own random stream
(:func:`view_seed`), so a resumed run writes what an uninterrupted one writes.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
from torch import nn

from ..io.atomic import replace_dir, write_text_atomic

KEY = "key.json"


def model_sha256(model: nn.Module) -> str:
    """sha256 of every parameter and buffer of ``model`` (names, shapes, dtypes and values)."""
    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        a = t.detach().cpu().contiguous().numpy()
        h.update(f"{name}{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def view_seed(seed: int, index: int) -> int:
    """The seed of test view ``index``'s random stream: a function of the eval's seed and the view alone, so a
    view renders the same whichever views were rendered before it (a resumed eval, a subset)."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1, np.uint64)[0] >> np.uint64(1))


class PartialViews:
    """The hidden folder of an output in progress, beside ``out``, for the settings ``key`` (JSON text)."""

    def __init__(self, out: Path, key: str) -> None:
        self.out = Path(out)
        self.folder = self.out.parent / f".{self.out.name}.partial"
        found = self.folder / KEY
        if self.folder.exists() and not (found.is_file() and found.read_text() == key):
            shutil.rmtree(self.folder)          # another model, other data or other settings: start over
        self.folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(found, key)

    def done(self, index: int) -> dict | None:
        """View ``index``'s record if an earlier run committed it (None otherwise)."""
        mark = self.folder / f"{index}.json"
        if not mark.is_file():
            return None
        try:
            return json.loads(mark.read_text())
        except ValueError:
            return None                          # a mark cut short is no mark: the view is rendered again

    def commit(self, index: int, record: dict) -> None:
        """Mark view ``index`` done (its files are already in :attr:`folder`)."""
        write_text_atomic(self.folder / f"{index}.json", json.dumps(record))

    def finish(self) -> None:
        """Drop the marks and the key, and move the folder onto ``out`` as a whole."""
        for p in self.folder.glob("*.json"):
            if p.name == KEY or p.stem.isdigit():
                p.unlink()
        replace_dir(self.folder, self.out)
