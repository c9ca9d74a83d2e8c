"""`occflownet quickstart`: the README's main job on a fresh machine, with no arguments.

The stages are :func:`occflownet.quickstart.run_quickstart` (the same library calls the verbs make, each
announced as its ``occflownet ...`` command); this module parses the options and prints where everything is.
"""
import argparse

HELP = "synthetic world -> train tiny (bounded time) -> eval -> export, on the embedded defaults"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="quickstart", help="folder for the world, the run and the model")
    p.add_argument("--scenes", type=int, default=3, help="synthetic scenes (the last one is the val split)")
    p.add_argument("--frames", type=int, default=16, help="keyframes per scene")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train-minutes", type=float, default=7.0, help="training time budget")
    p.add_argument("--max-steps", type=int, default=1000, help="step cap (about the time budget on a 2-core CPU)")
    p.add_argument("--voxel-mask", action=argparse.BooleanOptionalAction, default=True,
                   help="3D voxel losses only inside mask_camera (train --voxel-mask; default on: the quickest "
                        "recipe measured, docs/training.md)")
    p.add_argument("--supervision", default="3d", choices=["2d", "3d", "2d+3d"],
                   help="default 3d: within minutes on a CPU, 3D labels inside the camera mask give the model "
                        "closest to the street of the recipes measured; 2d needs a far longer budget "
                        "(docs/ablation.md, docs/training.md)")


def run(args) -> int:
    import sys

    from occflownet.data.tables import DatasetError
    from occflownet.export.onnx_export import ExportError
    from occflownet.quickstart import QuickstartConfig, run_quickstart
    from occflownet.train.loop import TrainingError

    cfg = QuickstartConfig(out=args.out, scenes=args.scenes, frames=args.frames, seed=args.seed,
                           train_minutes=args.train_minutes, max_steps=args.max_steps,
                           supervision=args.supervision, voxel_mask=args.voxel_mask)
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
