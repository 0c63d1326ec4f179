"""Entry point of ``cusfm``: dispatches subcommands, turns ``CusfmError`` into one line + exit 1.

Each subcommand module exposes ``add_parser(subparsers)`` (argument parsing) and
``run(args) -> int`` (the work), so tests can call either half.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Sequence

from cusfm_ros import __version__
from cusfm_ros.cli import (calibrate, convert, demo, evaluate, fleet, inspect, keyframes,
                           localize, map, map_update, match, models, report, simulate, vocab)
from cusfm_ros.cli.process_exit import exit_process
from cusfm_ros.errors import CusfmError
from cusfm_ros.pipeline.worker import CANCELLED_STATUS, Cancelled, raise_cancelled

SUBCOMMANDS = (simulate, convert, inspect, keyframes, map, map_update, fleet, localize,
               calibrate, match, models, vocab, evaluate, report, demo)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cusfm",
        description="Offline visual mapping, extrinsic refinement and localization "
                    "from ROS 2 bags (cuSfM design).")
    parser.add_argument("--version", action="version", version=f"cusfm {__version__}")
    loudness = parser.add_mutually_exclusive_group()
    loudness.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    loudness.add_argument("-q", "--quiet", action="store_true",
                          help="warnings and errors only (no progress)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in SUBCOMMANDS:
        module.add_parser(subparsers)
    return parser


def configure_logging(verbose: bool, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.getLogger("cusfm_ros").setLevel(level)  # also where logging is set up already
    logging.basicConfig(level=level,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


@contextlib.contextmanager
def _sigterm_unwinds():
    """SIGTERM (a supervisor, ``timeout``, ``docker stop``) unwinds the command as Ctrl-C
    does, so the run records where it stopped and its worker processes are shut down;
    without a handler the process died where it stood. Only the main thread can set it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    previous = signal.signal(signal.SIGTERM, raise_cancelled)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    try:
        with _sigterm_unwinds():
            return int(args.run(args) or 0)
    except CusfmError as exc:
        print(f"cusfm {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, Cancelled) as exc:  # every atomic write in progress dropped
        print(f"cusfm {args.command}: "
              f"{'interrupted' if isinstance(exc, KeyboardInterrupt) else 'terminated'}; "
              "nothing half-written was left, rerun the same command to resume",
              file=sys.stderr)
        return 130 if isinstance(exc, KeyboardInterrupt) else CANCELLED_STATUS


def console_main() -> None:
    """The ``cusfm`` console script: ``main`` on the command line's arguments, then the
    process's exit (``exit_process``)."""
    exit_process(main())


if __name__ == "__main__":
    console_main()
