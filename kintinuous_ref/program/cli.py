"""The `kintinuous` command: reconstruct, synth, evaluate, table, benchmark, warmup, convert,
download and info.

Heavy modules are imported inside the handlers so that `kintinuous --help` stays instant.
Errors meant for people (KintinuousError, and argparse's usage errors) become one line on stderr
and exit status 2; an OSError (a full disk, a folder that cannot be written) one line and 2;
SIGINT, SIGTERM and SIGHUP one line and 128 + the signal's number. Any other exception is a bug:
one line that says so, exit status 70, and the traceback in a crash log (reconstruct's in its
output folder, with the run's work kept). A command that did not do all that was asked (a
`table` with a failed run) exits with status 1.

    cli.py             the parser, the entry point main() and its one-line errors
    arguments.py       each command's arguments and help
    commands.py        each command's body
    config_options.py  --config FILE and --set KEY=VALUE over a command's defaults
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import NoReturn

from kintinuous_ref import __version__
from kintinuous_ref.errors import InternalError, KintinuousError
from kintinuous_ref.program import arguments, commands
from kintinuous_ref.program.arguments import (
    DEFAULT_ODOMETRY,
    FAST_ODOMETRY_HELP,
    MIRROR_VARIABLE,
    ODOMETRY_CHOICES,
    OTHER_SEQUENCES,
    PAPER_SEQUENCES,
    TUM_BASE_URL,
)
from kintinuous_ref.program.config_options import configured

__all__ = [
    "DEFAULT_ODOMETRY",
    "FAST_ODOMETRY_HELP",
    "MIRROR_VARIABLE",
    "ODOMETRY_CHOICES",
    "OTHER_SEQUENCES",
    "PAPER_SEQUENCES",
    "TUM_BASE_URL",
    "build_parser",
    "configured",
    "main",
]

# The algorithms multiply many small matrices (6xN systems, 3x3 rotations), for which a threaded
# BLAS costs more in wake-ups than it gains (docs/benchmarks.md, "Choices in the reference").
# Must be set before NumPy is first imported (the handlers import it lazily).
for _variable in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # OpenMP users keep their threads
    os.environ.setdefault(_variable, "1")


class _Parser(argparse.ArgumentParser):
    """argparse with its errors as one line, like every other error of the command."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"kintinuous: error: {message} (see {self.prog} --help)\n")


# The commands in the order --help lists them: each one's arguments and its body.
COMMANDS = (
    (arguments.add_synth, commands.run_synth),
    (arguments.add_evaluate, commands.run_evaluate),
    (arguments.add_reconstruct, commands.run_reconstruct),
    (arguments.add_table, commands.run_table),
    (arguments.add_info, commands.run_info),
    (arguments.add_benchmark, commands.run_benchmark),
    (arguments.add_warmup, commands.run_warmup),
    (arguments.add_convert, commands.run_convert),
    (arguments.add_download, commands.run_download),
    (arguments.add_course, commands.run_course),
)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="kintinuous",
        description="Dense RGB-D mapping with robust visual odometry (Whelan et al., ICRA 2013).",
    )
    parser.add_argument("--version", action="version", version=f"kintinuous {__version__}")
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    for add, handler in COMMANDS:
        add(subparsers).set_defaults(handler=handler)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # SystemExit: --help, --version or a one-line usage error
    if not hasattr(args, "handler"):
        parser.print_help()
        return 1
    from kintinuous_ref.signals import Interrupted, handle_signals

    try:
        with handle_signals():
            status = args.handler(args)
    except InternalError as err:
        print(f"kintinuous: {err}", file=sys.stderr)  # it says that it is a bug
        return 70
    except KintinuousError as err:
        print(f"kintinuous: error: {err}", file=sys.stderr)
        return 2
    except Interrupted as stop:
        print(
            f"kintinuous: {stop.message or f'interrupted by {stop.signal_name}'}", file=sys.stderr
        )
        return stop.exit_status
    except KeyboardInterrupt:
        print("kintinuous: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(
            "kintinuous: error: out of memory (ask for fewer or smaller frames, or a smaller "
            "volume)",
            file=sys.stderr,
        )
        return 2
    except OSError as err:
        where = f"{err.filename}: " if err.filename else ""
        print(f"kintinuous: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2
    except Exception as err:
        log = _crash_log()
        print(
            f"kintinuous: internal error (a bug, please report it): {type(err).__name__}: "
            f"{err}; traceback in {log}",
            file=sys.stderr,
        )
        return 70
    return status if isinstance(status, int) else 0


def _crash_log() -> str:
    """The current exception's traceback in a new file in the temporary folder; its path."""
    import tempfile
    import traceback

    try:
        handle, path = tempfile.mkstemp(prefix="kintinuous-crash-", suffix=".log")
        with os.fdopen(handle, "w") as log:
            log.write(traceback.format_exc())
        return path
    except OSError:
        return "nowhere (the temporary folder cannot be written)"


if __name__ == "__main__":
    sys.exit(main())
