"""The ``vi3`` console command. Each subcommand lives in ``vi3_ros.commands.<name>`` with a ``register``."""

from __future__ import annotations

import argparse
import importlib
import sys

from vi3_ros import interrupts

SUBCOMMANDS = ("bench", "demo", "replay", "eval", "calib", "reference", "make_bag")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vi3", description="VI3: IMU-anchored metric geometry from 3D foundation "
                                     "models (replay, evaluation, benchmarks, data generation).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"vi3_ros.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; a signal while it runs ends it with 128 + the signal's number, after it unwound (a command
    that writes an output reports what it kept; any other says it was interrupted)."""
    args = build_parser().parse_args(argv)
    interrupts.set_phase(interrupts.RUNNING)
    try:
        with interrupts.trapped() as trap:
            try:
                return int(args.func(args) or 0)
            except (KeyboardInterrupt, ImportError) as exc:
                # a signal while an extension module initialises surfaces as an ImportError raised from it
                if isinstance(exc, ImportError) and not isinstance(exc.__cause__, KeyboardInterrupt):
                    raise
                print(f"vi3 {args.command}: interrupted by {trap.name}", file=sys.stderr)
                return trap.status
    finally:
        interrupts.set_phase(interrupts.FINISHED)


def program() -> None:
    """The ``vi3`` program: SIGINT and SIGTERM end it with status 130 / 143 at any moment, without a traceback
    (``vi3_ros.interrupts``)."""
    interrupts.exit_on_signal()
    interrupts.end(main())


if __name__ == "__main__":
    program()
