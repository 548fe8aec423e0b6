"""Narrow the ``[tool.mutmut]`` configuration of a copied tree to one scope (used by ``make mutants``).

    python tests/mutmut_scope.py build/mutmut/pyproject.toml SCOPE[,SCOPE...]

rewrites that file's ``[tool.mutmut]`` section so mutmut mutates only the scopes' source files and runs
only their test files (``all``: the section as it is). Run it on the copy under build/, never on the
repository's own pyproject.toml. The scopes and their tests are listed in docs/testing.md.
"""
from __future__ import annotations

import json
import re
import sys
import tomllib
from pathlib import Path

FIT_UNIT_TESTS = ["tests/test_fit.py::test_smoothness_prior_compares_neighbours_in_the_tangent_plane",
                  "tests/test_fit.py::test_secondary_buffer_is_a_ring"]
"""test_fit.py's tests of the losses that run no fit (a fit per mutant would take hours)"""

EVAL_TESTS = ["tests/test_metrics.py", "tests/test_catches_mutants.py", "tests/test_catches_eval_per_view.py"]

SCOPES: dict[str, tuple[list[str], list[str]]] = {
    "checkpoints": (["src/nefii/io/checkpoints.py"], ["tests/test_catches_seeded_bugs.py", "tests/test_catches_mutants.py"]),
    "losses": (["src/nefii/fit/losses.py"], ["tests/test_catches_seeded_bugs.py", "tests/test_catches_mutants.py",
                                             "tests/test_estimator.py", *FIT_UNIT_TESTS]),
    "metrics": (["src/nefii/evaluate/metrics.py"], EVAL_TESTS),
    "table1": (["src/nefii/evaluate/table1.py"], EVAL_TESTS),
    "evaluate": (["src/nefii/evaluate/*"], EVAL_TESTS),
    "fields": (["src/nefii/fields/*"], ["tests/test_fields.py", "tests/test_catches_seeded_bugs.py",
                                        "tests/test_catches_mutants.py"]),
    "render": (["src/nefii/render/*"], ["tests/test_brdf.py", "tests/test_estimator.py", "tests/test_samplers_chi2.py",
                                        "tests/test_sg.py", "tests/test_envmap.py"]),
}
"""scope -> (only_mutate globs, test files)"""


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def narrow(pyproject: Path, scopes: str) -> None:
    names = [s for s in scopes.split(",") if s]
    if names == ["all"]:
        return
    unknown = [s for s in names if s not in SCOPES]
    if unknown or not names:
        raise SystemExit(f"unknown mutmut scope {scopes!r} (known: all, {', '.join(SCOPES)})")
    text = pyproject.read_text()
    section = dict(tomllib.loads(text)["tool"]["mutmut"])
    section["only_mutate"] = list(dict.fromkeys(g for s in names for g in SCOPES[s][0]))
    section["pytest_add_cli_args_test_selection"] = list(dict.fromkeys(t for s in names for t in SCOPES[s][1]))
    body = "\n".join(f"{k} = {_toml_value(v)}" for k, v in section.items())
    # the section runs from its header to the next table header or the end of the file
    new, n = re.subn(r"^\[tool\.mutmut\]\n(?:(?!^\[).*\n?)*", "[tool.mutmut]\n" + body + "\n\n", text,
                     flags=re.MULTILINE)
    if n != 1:
        raise SystemExit(f"{pyproject}: no single [tool.mutmut] section")
    pyproject.write_text(new)


if __name__ == "__main__":
    narrow(Path(sys.argv[1]), sys.argv[2])
