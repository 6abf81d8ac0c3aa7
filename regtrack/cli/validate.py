"""``regtrack validate CASE``: check a case folder and print its summary or its problems."""

from __future__ import annotations

import argparse
import sys

HELP = "check a case folder (case.toml and its inputs) and summarise it"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case", metavar="CASE", help="case folder, or the path of its case.toml")
    parser.add_argument("--shallow", action="store_true",
                        help="check case.toml and that the files exist, without opening them")


def run(args: argparse.Namespace) -> int:
    """Exit 0 and print the summary when the case is valid; exit 2 and list every problem
    (one line each, naming ``case.toml [section] key``) when it is not.  Writes nothing."""
    import logging

    from regtrack.case import format_summary, load_case
    from regtrack.errors import CaseError

    # the summary / problem list is the output: keep the loggers quiet meanwhile (warnings
    # would print twice, reader INFO lines would clutter the screen); --debug shows all
    quiet = {} if getattr(args, "debug", False) else {
        "regtrack.case.loader": logging.ERROR, "regtrack.imaging": logging.WARNING}
    saved = {name: logging.getLogger(name).level for name in quiet}
    try:
        for name, level in quiet.items():
            logging.getLogger(name).setLevel(level)
        case = load_case(args.case, deep=not args.shallow)
    except CaseError as err:
        problems = err.problems
        warnings = getattr(err, "warnings", [])
        print(f"{args.case}: invalid case, {len(problems)} problem(s):", file=sys.stderr)
        for p in problems:
            print(f"  error: {p}", file=sys.stderr)
        for w in warnings:
            print(f"  warning: {w}", file=sys.stderr)
        return err.exit_code
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)
    print(format_summary(case))
    return 0
