"""The ``vi3`` console command. Each subcommand lives in ``vi3_ros.commands.<name>`` with a ``register``."""

from __future__ import annotations

import argparse
import importlib

from vi3_ros import interrupts

SUBCOMMANDS = ("bench", "demo", "replay", "eval", "make_bag")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vi3", description="VI3: IMU-anchored metric geometry from 3D foundation "
                                     "models (replay, evaluation, benchmarks, data generation).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"vi3_ros.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    interrupts.set_phase(interrupts.RUNNING)
    try:
        return int(args.func(args) or 0)
    finally:
        interrupts.set_phase(interrupts.FINISHED)


def program() -> None:
    """The ``vi3`` program: SIGTERM ends it with status 143 at any moment (``vi3_ros.interrupts``)."""
    interrupts.exit_on_signal()
    interrupts.end(main())


if __name__ == "__main__":
    program()
