"""The ``selfcal`` command line.

Each sub-command lives in ``selfcal/commands/<name>.py`` and provides
``add_arguments(parser)`` and ``run(args) -> int``. Exit codes: 0 done, 1 refused or
failed (for example no calibration could be published), 2 usage or input error (a
one-line reason on stderr, never a traceback). A closed output pipe ends quietly.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from pydantic import ValidationError

from selfcal.blas_threads import one_blas_thread
from selfcal.errors import InputError, SelfcalError

#: Sub-commands in help order: name -> one-line help.
COMMANDS = {
    "calibrate": "run the online calibrator over a recording and print/save the calibration",
    "apply": "write a recording with calibrated specific force in g",
    "diagnose": "measured vs simulated: find what the base model misses",
    "simulate": "write a simulated insole recording and its truth",
    "replay": "long-horizon replay of simulated wear, or of a recorded file (--recording), against the truth",
    "serve": "start the calibration service (FastAPI; SQLite, or PostgreSQL with many processes)",
    "worker": "a refit worker process for a shared PostgreSQL database",
    "gateway": "run the BLE gateway that forwards insole streams to the service",
    "demo": "the whole system end to end: service, virtual insoles, gateway",
}


def build_parser() -> argparse.ArgumentParser:
    """The top-level argument parser with every available sub-command."""
    from selfcal import __version__

    parser = argparse.ArgumentParser(prog="selfcal", description=__doc__.splitlines()[0],
                                     epilog="exit codes: 0 done; 1 refused or failed; 2 usage or input error")
    parser.add_argument("--version", action="version", version=f"selfcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        try:
            module = importlib.import_module(f"selfcal.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"selfcal.commands.{name}":
                continue  # not built yet
            raise
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--config", metavar="FILE", help="TOML file overriding selfcal/configs/default.toml")
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``selfcal`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    # small matrices: OpenBLAS's extra threads only busy-wait beside the server, workers or
    # other replays (selfcal.blas_threads); a count set in the environment is kept
    one_blas_thread()
    try:
        code = int(args._run(args) or 0)
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        # the reader closed the pipe (``selfcal ... --json | head -1``): the work is done,
        # only its reader stopped; no traceback, and nothing more is written
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except InputError as exc:
        print(f"selfcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:  # a configuration section (or file) with a wrong key or value
        what = "; ".join(f"{'.'.join(str(x) for x in e['loc']) or exc.title}: {e['msg']}" for e in exc.errors()[:3])
        print(f"selfcal {args.command}: error: invalid setting ({exc.title}): {what}", file=sys.stderr)
        return 2
    except SelfcalError as exc:
        print(f"selfcal {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"selfcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
