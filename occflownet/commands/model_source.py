"""The model-source options shared by `export` and `predict`: a checkpoint, a randomly initialised preset, or (for
`predict`) an exported ONNX file."""
import argparse

from occflownet.choices import PRESET_NAMES


def add_model_source(parser: argparse.ArgumentParser, onnx: bool = False) -> None:
    """Exactly one of ``--checkpoint`` / ``--preset`` (with ``--random-init``, ``--seed``) / ``--model`` (if
    ``onnx``)."""
    src = parser.add_mutually_exclusive_group(required=True)
    if onnx:
        src.add_argument("--model", help="exported ONNX model (onnxruntime only, no torch needed)")
    src.add_argument("--checkpoint", help="torch checkpoint written by `occflownet train`")
    src.add_argument("--preset", choices=PRESET_NAMES, help="randomly initialised preset (needs --random-init)")
    parser.add_argument("--random-init", action="store_true", help="with --preset: random weights from --seed")
    parser.add_argument("--seed", type=int, default=0, help="seed for --random-init (default 0)")


def source_problem(args: argparse.Namespace) -> str | None:
    """Why the parsed model source cannot be used (None when it can)."""
    if args.preset and not args.random_init:
        alternatives = "--checkpoint / --model" if hasattr(args, "model") else "--checkpoint"
        return f"--preset needs --random-init (or use {alternatives})"
    return None
