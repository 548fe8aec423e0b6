"""What resume relies on in nefii.io.checkpoints: the newest by step, killed writes ignored, a corrupt newest
passed over for the one before, a checkpoint that asks for code refused."""
from __future__ import annotations

import os

import pytest
import torch

from nefii.errors import InputError
from nefii.io.atomic import atomic_path
from nefii.io.checkpoints import latest_checkpoint, list_checkpoints, load_latest_checkpoint, save_checkpoint
from nefii.io.safe_load import UnsafeFileError, load_tensors


def _state(step: int) -> dict:
    return {"step": step, "w": torch.full((2,), float(step))}


class Payload:
    """A pickle that runs ``touch MARKER`` when unpickled without restrictions."""

    def __init__(self, marker) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_resume_picks_the_newest_of_three(tmp_path):
    for step in (40, 7, 1200):                       # written out of order, names of different widths
        save_checkpoint(tmp_path, step, _state(step), keep=3)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step_0000007.pt", "step_0000040.pt", "step_0001200.pt"]
    found = load_latest_checkpoint(tmp_path)
    assert found is not None and found.path.name == "step_0001200.pt" and found.step == 1200
    assert found.state["w"].tolist() == [1200.0, 1200.0]


def test_steps_are_ordered_as_numbers_past_seven_digits(tmp_path):
    for step in (9_999_999, 10_000_000, 200_000_000):
        save_checkpoint(tmp_path, step, _state(step), keep=2)
    # as text "step_10000000.pt" < "step_200000000.pt" < "step_9999999.pt": the wrong ones would survive
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step_10000000.pt", "step_200000000.pt"]
    assert latest_checkpoint(tmp_path).name == "step_200000000.pt"
    assert load_latest_checkpoint(tmp_path).step == 200_000_000


def test_a_killed_writes_temporary_is_ignored_and_removed(tmp_path):
    for step in (10, 20):
        save_checkpoint(tmp_path, step, _state(step), keep=3)
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(tmp_path / "step_0000030.pt") as tmp:
            stale = tmp
            raise KeyboardInterrupt
    stale.write_bytes(b"half a checkpoint")          # what a SIGKILL (no clean-up) leaves
    found = load_latest_checkpoint(tmp_path)
    assert found.step == 20 and not stale.exists()


@pytest.mark.parametrize("damage", ["truncated", "empty", "not a checkpoint"])
def test_a_corrupt_newest_falls_back_to_the_one_before_and_says_so(tmp_path, damage):
    for step in (10, 20, 30):
        save_checkpoint(tmp_path, step, _state(step), keep=3)
    newest = tmp_path / "step_0000030.pt"
    if damage == "truncated":
        newest.write_bytes(newest.read_bytes()[:100])
    elif damage == "empty":
        newest.write_bytes(b"")
    else:
        torch.save({"w": torch.zeros(2)}, newest)
    said = []
    found = load_latest_checkpoint(tmp_path, warn=said.append)
    assert found.step == 20 and found.path.name == "step_0000020.pt"
    assert len(said) == 1 and "step_0000030.pt" in said[0] and "\n" not in said[0]


def test_none_when_no_checkpoint_loads(tmp_path):
    assert load_latest_checkpoint(tmp_path / "absent") is None
    (tmp_path / "step_0000001.pt").write_bytes(b"")
    assert load_latest_checkpoint(tmp_path) is None


def test_a_checkpoint_that_asks_for_code_is_refused_not_passed_over(tmp_path):
    save_checkpoint(tmp_path, 10, _state(10))
    marker = tmp_path / "MARKER"
    torch.save({"step": 20, "w": Payload(marker)}, tmp_path / "step_0000020.pt")
    with pytest.raises(UnsafeFileError) as info:
        load_latest_checkpoint(tmp_path)
    assert "step_0000020.pt" in str(info.value) and "\n" not in str(info.value)
    assert not marker.exists()


def test_load_tensors_reads_what_nefii_writes_and_refuses_the_rest(tmp_path):
    torch.save({"a": torch.ones(3), "b": [1, 2.5, "x", None, (1, 2)], "c": {"d": True}}, tmp_path / "ok.pt")
    assert load_tensors(tmp_path / "ok.pt")["b"] == [1, 2.5, "x", None, (1, 2)]
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(InputError, match="not a dict"):
        load_tensors(tmp_path / "list.pt")
    with pytest.raises(InputError, match="file not found"):
        load_tensors(tmp_path / "absent.pt")
