"""``vi3 demo``: the README's demo (replay + evaluation on the bundled bag)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run replay and evaluation on the bundled bag")
    p.add_argument("--out", default="out/demo", help="output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    print("vi3 demo: not yet available (needs the replay and evaluation issues); nothing was run.")
    return 0
