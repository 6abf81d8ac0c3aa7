"""The ``regtrack`` command line.

Each verb lives in its own module ``regtrack/cli/<verb>.py`` that defines

* ``HELP``: one line for ``regtrack --help``;
* ``add_arguments(parser)``: its options (argparse only, no heavy imports);
* ``run(args) -> int``: the work; heavy modules are imported inside it.

so ``regtrack --help`` returns at once.  User errors (:class:`regtrack.errors.RegtrackError`)
end as one line on stderr and a non-zero exit code; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# verb -> module.  Stages that do not exist yet are simply not listed.
COMMANDS: dict[str, str] = {
    "run": "regtrack.cli.run",
    "mesh": "regtrack.cli.mesh",
    "validate": "regtrack.cli.validate",
    "study": "regtrack.cli.study",
    "calibrate": "regtrack.cli.calibrate",
    "project": "regtrack.cli.project",
    "mammogram": "regtrack.cli.mammogram",
    "simulate": "regtrack.cli.simulate",
    "track": "regtrack.cli.track",
    "surrogate": "regtrack.cli.surrogate",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="regtrack",
        description="Track breast lesions between prone MRI and mammograms through "
        "patient-specific finite-element simulation.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for verb, modname in COMMANDS.items():
        mod = importlib.import_module(modname)
        p = sub.add_parser(verb, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_module=modname)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from regtrack import __version__

        print(f"regtrack {__version__}")
        return 0
    if not getattr(args, "command", None):
        parser.print_help()
        return 1
    level = logging.DEBUG if args.debug else (logging.WARNING if args.quiet else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    mod = importlib.import_module(args._module)
    import threading

    from regtrack._signals import Terminated, install_cli_handlers, restore_handlers
    from regtrack.errors import RegtrackError

    main_thread = threading.current_thread() is threading.main_thread()
    # SIGTERM unwinds like Ctrl-C: workers stopped, temporaries removed
    previous = install_cli_handlers() if main_thread else None
    try:
        return int(mod.run(args) or 0)
    except RegtrackError as err:
        if args.debug:
            raise
        print(f"regtrack {args.command}: error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt as exc:
        what = f"terminated ({exc})" if isinstance(exc, Terminated) else "interrupted"
        print(f"regtrack {args.command}: {what}; worker processes stopped, unfinished stages "
              "discarded (finished ones stay in the cache)", file=sys.stderr)
        return 128 + exc.signum if isinstance(exc, Terminated) else 130
    finally:
        if previous is not None:
            restore_handlers(previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
