"""`occflownet export`: export a model to ONNX with parity check."""
from ._pending import not_yet

HELP = "export a model to ONNX with parity check"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("export", 3)
