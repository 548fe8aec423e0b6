"""The views an interrupted ``nefii eval`` already scored, kept so that a rerun goes on from them.

An eval of a large test set runs for hours on a CPU (200 views at 512 x 512 take about a minute each on two
cores). Each scored view is committed to a hidden folder beside the eval's (``RUN/.eval.partial``): its EXRs
and grid first, then ``K.json`` (its entry of ``metrics.json``) as the commit mark. A rerun with the same
model, test data and settings (the folder's ``key.json``) scores only the views without a mark; anything
else clears the folder. Every view renders from its own random stream (:func:`view_seed`), so a resumed eval
writes what an uninterrupted one writes.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from torch import nn

from ..data.fingerprint import fingerprint
from ..data.scene import SceneData
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


@dataclass(frozen=True)
class EvalKey:
    """What an eval's per-view results depend on."""

    model: str
    """sha256 of the model's parameters and buffers"""
    cameras: str
    """sha256 of the test views' poses, intrinsics and size"""
    images: str
    """sha256 of the test images as loaded (after any downscale)"""
    views: tuple[int, ...]
    """the test views' indices scored"""
    spp: int
    seed: int
    device: str
    """``cpu`` or ``cuda``: their floating point differs"""

    @staticmethod
    def of(model: nn.Module, scene: SceneData, views: list[int], spp: int, seed: int, device: str) -> "EvalKey":
        data = fingerprint(scene, None)
        return EvalKey(model_sha256(model), data.cameras, data.images, tuple(views), spp, seed, device)

    def to_json(self) -> str:
        return json.dumps({**asdict(self), "views": list(self.views)}, sort_keys=True)


class PartialEval:
    """The hidden folder of an eval in progress, beside ``out``."""

    def __init__(self, out: Path, key: EvalKey) -> None:
        self.out = Path(out)
        self.folder = self.out.parent / f".{self.out.name}.partial"
        text = key.to_json()
        found = self.folder / KEY
        if self.folder.exists() and not (found.is_file() and found.read_text() == text):
            shutil.rmtree(self.folder)          # another model, other data or other settings: start over
        self.folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(found, text)

    def scored(self, index: int) -> dict | None:
        """View ``index``'s entry of metrics.json if an earlier run committed it (None otherwise)."""
        mark = self.folder / f"{index}.json"
        if not mark.is_file():
            return None
        try:
            return json.loads(mark.read_text())
        except ValueError:
            return None                          # a mark cut short is no mark: the view is scored again

    def commit(self, index: int, entry: dict) -> None:
        """Mark view ``index`` scored (its files are already in :attr:`folder`)."""
        write_text_atomic(self.folder / f"{index}.json", json.dumps(entry))

    def finish(self) -> None:
        """Drop the marks and the key, and move the folder onto ``out`` as a whole."""
        for p in self.folder.glob("*.json"):
            if p.name == KEY or p.stem.lstrip("-").isdigit():
                p.unlink()
        replace_dir(self.folder, self.out)
