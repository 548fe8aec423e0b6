"""three.js for ``nefii view``: one pinned release of the npm package, never committed.

Where it comes from, first found wins:

1. ``--three PATH`` or ``$NEFII_THREE``: the npm tarball (``three-VERSION.tgz``, checked against
   the registry's sha512) or an unpacked package folder (``node_modules/three``, version checked);
2. the cache, ``$NEFII_CACHE_DIR`` or ``$XDG_CACHE_HOME/nefii`` or ``~/.cache/nefii``;
3. fetched once into the cache by ``npm pack three@VERSION`` where ``npm`` is installed
   (the npm registry), checked, then reused offline.

The page needs four modules (three, OrbitControls, GLTFLoader, EXRLoader) and what they import;
``module_sources`` returns them with every relative import rewritten to a bare specifier, so the
page can serve them all from one import map of ``data:`` URLs and work from ``file://`` offline.
"""
from __future__ import annotations

import base64
import hashlib
import json
import os
import posixpath
import re
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path
from typing import Callable

from ..errors import InputError

THREE_VERSION = "0.187.0"
THREE_INTEGRITY = "sha512-Qiu7R+Cmh8CstZsY1uJOSWnVlfo7ZtNLV7mF8Jltk3LB3AtDu9cRZlcnRKkAk8Y4z6KKw35z7Y7Urd7jWY8etA=="
"""``npm view three@0.187.0 dist.integrity``"""
ENTRY_FILES = ("build/three.module.js", "examples/jsm/controls/OrbitControls.js",
               "examples/jsm/loaders/GLTFLoader.js", "examples/jsm/loaders/EXRLoader.js")
"""package paths the page imports; their own imports are followed"""

_IMPORT = re.compile(r"""(\b(?:from|import)\s*\(?\s*)(['"])(\.{1,2}/[^'"\n]+)\2""")


def cache_dir() -> Path:
    if os.environ.get("NEFII_CACHE_DIR"):
        return Path(os.environ["NEFII_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nefii"


def tarball_name() -> str:
    return f"three-{THREE_VERSION}.tgz"


def specifier(package_path: str) -> str:
    """The import-map key of a file of the package: ``three`` for the main module."""
    return "three" if package_path == "build/three.module.js" else f"three/{package_path}"


class ThreeSource:
    """Files of the three package, read from its npm tarball or an unpacked folder."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._tar = tarfile.open(path, "r:gz") if path.is_file() else None

    def read(self, package_path: str) -> str:
        try:
            if self._tar is not None:
                member = self._tar.extractfile(f"package/{package_path}")
                if member is None:
                    raise KeyError(package_path)
                return member.read().decode("utf-8")
            return (self.path / package_path).read_text(encoding="utf-8")
        except (KeyError, FileNotFoundError):
            raise InputError(self.path, f"three.js package has no {package_path}") from None


def _integrity(path: Path) -> str:
    return "sha512-" + base64.b64encode(hashlib.sha512(path.read_bytes()).digest()).decode()


def _checked(path: Path) -> ThreeSource:
    if path.is_dir():
        try:
            version = json.loads((path / "package.json").read_text())["version"]
        except (OSError, ValueError, KeyError):
            raise InputError(path, "not a three.js package folder (no package.json with a version)") from None
        if version != THREE_VERSION:
            raise InputError(path, f"three.js {version}; nefii view is built and tested with {THREE_VERSION}")
        return ThreeSource(path)
    if not path.is_file():
        raise InputError(path, "not found")
    if _integrity(path) != THREE_INTEGRITY:
        raise InputError(path, f"is not the npm registry's three-{THREE_VERSION}.tgz (sha512 differs)")
    return ThreeSource(path)


def fetch_three(cache: Path, log: Callable[[str], None] = print) -> Path:
    """``npm pack three@VERSION`` into ``cache`` (atomically, integrity checked); returns the tarball."""
    npm = shutil.which("npm")
    if npm is None:
        raise InputError(cache / tarball_name(), "not cached, and npm is not installed to fetch it")
    cache.mkdir(parents=True, exist_ok=True)
    log(f"fetching three.js {THREE_VERSION} from the npm registry into {cache} (once)")
    with tempfile.TemporaryDirectory(dir=cache, prefix=".three.") as tmp:
        try:
            subprocess.run([npm, "pack", f"three@{THREE_VERSION}", "--pack-destination", tmp, "--silent"],
                           check=True, capture_output=True, text=True, timeout=600)
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as e:
            err = getattr(e, "stderr", "") or str(e)
            raise InputError(cache / tarball_name(), f"`npm pack three@{THREE_VERSION}` failed: "
                                                     f"{err.strip().splitlines()[-1] if err.strip() else e}") from None
        got = Path(tmp) / tarball_name()
        _checked(got)
        os.replace(got, cache / tarball_name())
    return cache / tarball_name()


def locate_three(explicit: Path | None = None, fetch: bool = True,
                 log: Callable[[str], None] = print) -> ThreeSource:
    """The pinned three.js release (see the module doc for the order); raises InputError saying how to get it."""
    given = explicit or (Path(os.environ["NEFII_THREE"]) if os.environ.get("NEFII_THREE") else None)
    if given is not None:
        return _checked(given)
    cached = cache_dir() / tarball_name()
    if cached.is_file():
        return _checked(cached)
    if not fetch:
        raise InputError(cached, "three.js is not cached")
    try:
        return _checked(fetch_three(cache_dir(), log))
    except InputError as e:
        raise InputError(cached, f"{e.problem}. Get it on a machine with npm: `npm pack three@{THREE_VERSION}`, "
                                 f"and put the .tgz there or pass it with --three") from None


def module_sources(src: ThreeSource) -> dict[str, str]:
    """Import-map key -> module text, for the entry files and everything they import."""
    out: dict[str, str] = {}
    todo = list(ENTRY_FILES)
    while todo:
        path = todo.pop()
        if specifier(path) in out:
            continue
        text = src.read(path)

        def rewrite(m: re.Match, base: str = posixpath.dirname(path)) -> str:
            dep = posixpath.normpath(posixpath.join(base, m.group(3)))
            todo.append(dep)
            return f"{m.group(1)}{m.group(2)}{specifier(dep)}{m.group(2)}"

        out[specifier(path)] = _IMPORT.sub(rewrite, text)
    return out
