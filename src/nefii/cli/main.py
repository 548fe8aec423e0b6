"""``nefii VERB ...``: the one console script.

Each verb is a module with ``add_parser(subparsers)`` (which sets ``func``) and its own ``run``.
Bad input raises :class:`nefii.errors.InputError` and ends here as one line on stderr, exit 2.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from importlib import import_module

from ..errors import InputError

VERBS = ("synth", "geometry", "fit", "refine", "eval", "relight", "export", "view", "demo")
"""verb modules under nefii.cli, in the order ``nefii --help`` lists them"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nefii", description="NeFII inverse rendering.")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    for verb in VERBS:
        import_module(f"nefii.cli.{verb}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def one_line(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"nefii {args.verb}: warning: {message}", file=sys.stderr)

    try:
        with warnings.catch_warnings():      # warnings (suspicious but legitimate input) as one line each
            warnings.showwarning = one_line
            return int(args.func(args) or 0)
    except InputError as e:
        print(f"nefii {args.verb}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"nefii {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
