"""`occflownet quickstart`: the README's main job on a fresh machine, with no arguments.

The stages are :func:`occflownet.quickstart.run_quickstart` (the same library calls the verbs make, each
announced as its ``occflownet ...`` command); this module parses the options and prints where everything is.
"""
import argparse

from occflownet.options import add_options, config_kwargs
from occflownet.quickstart import QuickstartConfig

HELP = "synthetic world -> train small (bounded time) -> eval -> export, on the embedded defaults"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The fields of QuickstartConfig (occflownet/options.py)."""
    add_options(p, QuickstartConfig)


def run(args) -> int:
    import sys

    from occflownet.data.tables import DatasetError
    from occflownet.export.onnx_export import ExportError
    from occflownet.quickstart import run_quickstart
    from occflownet.train.loop import TrainingError

    try:
        cfg = QuickstartConfig(**config_kwargs(args, QuickstartConfig))
    except ValueError as e:                             # values the parser cannot check alone
        print(f"occflownet quickstart: {e}", file=sys.stderr)
        return 2
    try:
        done = run_quickstart(cfg)
    except (DatasetError, TrainingError, ExportError, FileNotFoundError, FileExistsError, ValueError, OSError) as e:
        print(f"occflownet quickstart: {e}", file=sys.stderr)
        return 1
    p = done["paths"]
    print(f"""
quickstart finished in {done['minutes']:.1f} min.
  synthetic world   {p.world}   (previews: {p.world / 'preview'})
  training run      {p.run}   (log.jsonl, checkpoints/last.pt)
  evaluation        {p.eval_json}
  picture           {p.picture}   (ground truth beside the prediction, first val keyframe)
  3D viewer         {p.viewer}   (the same keyframe in 3D: open it in a browser)
  ONNX model        {p.onnx}

next:
  occflownet predict --model {p.onnx} --images {p.example} --calib {p.example / 'calib.json'} --out grid.npz --png bev.png --html view.html
  occflownet serve --model {p.onnx} --port 8000""")
    return 0
