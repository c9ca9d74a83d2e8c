"""`occflownet eval`: evaluate a checkpoint or ONNX model."""
from ._pending import not_yet

HELP = "evaluate a checkpoint or ONNX model"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("eval", 6)
