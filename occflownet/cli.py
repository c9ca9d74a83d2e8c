"""The ``occflownet`` command line: one sub-command per verb (docs/contracts.md)."""
from __future__ import annotations

import argparse
import sys

from occflownet import __version__
from occflownet.commands import eval as eval_cmd
from occflownet.commands import export, labels, predict, prepare, quickstart, recipes, serve, synth, train, view

VERBS = {
    "synth": synth, "labels": labels, "prepare": prepare, "recipes": recipes, "train": train, "eval": eval_cmd, "export": export,
    "predict": predict, "serve": serve, "quickstart": quickstart, "view": view,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="occflownet", description="Camera-only 3D semantic occupancy (OccFlowNet).")
    parser.add_argument("--version", action="version", version=f"occflownet {__version__}")
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for name, module in VERBS.items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
