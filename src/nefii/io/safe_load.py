"""Reading ``.pt`` files without trusting them: tensors and plain values only, never code.

Run folders are shared between people, so ``model.pt``, ``sdf.pt`` and checkpoints are untrusted input.
``torch.load(weights_only=True)`` unpickles only tensors, dicts, lists, tuples, strings and numbers; a file
whose pickle names anything else (``os.system`` in a ``__reduce__``, a class) is refused before any of it
runs. Every file nefii writes holds only such values, so nothing it wrote is refused.
"""
from __future__ import annotations

import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from ..errors import InputError


class UnsafeFileError(InputError):
    """A ``.pt`` whose pickle asks for more than tensors and plain values: refused, never a fallback."""


def load_tensors(path: str | Path, map_location: torch.device | str = "cpu") -> dict[str, Any]:
    """The dict saved in ``path``; a file that is not one (code in its pickle, truncated, empty, another
    format) raises :class:`InputError` naming it, one line
    (:class:`UnsafeFileError` when it asks for code)."""
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")          # torch's notes on pickle protocols are not the user's
            blob = torch.load(path, map_location=map_location, weights_only=True)
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except pickle.UnpicklingError:
        raise UnsafeFileError(path, "refused: it holds Python objects other than tensors and plain values, and "
                               "loading them could run code (nefii never writes such files)") from None
    except Exception as e:  # torch raises EOFError, RuntimeError (zip), KeyError (not a pickle), ...
        first = str(e).splitlines()[0][:120] if str(e) else ""
        raise InputError(path, f"truncated, empty or not a PyTorch file ({type(e).__name__}"
                               f"{': ' + first if first else ''})") from None
    if not isinstance(blob, dict):
        raise InputError(path, f"not a nefii file: holds a {type(blob).__name__}, not a dict")
    return blob
