"""`occflownet serve`: serve an ONNX model over HTTP."""
from ._pending import not_yet

HELP = "serve an ONNX model over HTTP"


def add_arguments(parser):
    pass


def run(args) -> int:
    return not_yet("serve", 7)
