"""`occflownet quickstart`: the README's main job on a fresh machine, with no arguments.

synthetic world → prepare → train `tiny` for a bounded time → eval → export (with its parity check), then print
where everything is and how to `predict` and `serve`. Each stage is the ordinary command-line verb, printed
before it runs, so the quickstart doubles as a transcript of the workflow.
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
    import contextlib
    import io
    import shlex
    import sys
    import time
    from pathlib import Path

    from occflownet.cli import main as cli

    out = Path(args.out).resolve()
    world, run_dir, onnx = out / "world", out / "run", out / "model.onnx"
    ckpt = run_dir / "checkpoints" / "last.pt"
    stages = []
    if not (world / "v1.0-trainval" / "sample.json").is_file():
        stages.append(["synth", "--out", str(world), "--scenes", str(args.scenes), "--frames", str(args.frames),
                       "--seed", str(args.seed), "--preview"])
    stages += [
        ["prepare", "--dataroot", str(world)],
        ["train", "--preset", "tiny", "--dataroot", str(world), "--out", str(run_dir), "--split", "train",
         "--supervision", args.supervision, "--flow" if args.supervision != "3d" else "--no-flow",
         "--time-limit", str(args.train_minutes * 60),
         "--max-steps", str(args.max_steps), "--resume", "--seed", str(args.seed),
         "--voxel-mask" if args.voxel_mask else "--no-voxel-mask"],
        ["eval", "--checkpoint", str(ckpt), "--dataroot", str(world), "--split", "val",
         "--save-predictions", str(out / "predictions"), "--output", str(out / "eval.json")],
        ["export", "--checkpoint", str(ckpt), "--out", str(onnx)],
    ]
    t0 = time.monotonic()
    for n, argv in enumerate(stages, 1):
        print(f"\n[{n}/{len(stages)}] occflownet {shlex.join(argv)}", file=sys.stderr, flush=True)
        if argv[0] == "eval":  # the table goes to stderr and the JSON to --output; keep stdout for the summary
            with contextlib.redirect_stdout(io.StringIO()):
                rc = cli(argv)
        else:
            rc = cli(argv)
        if rc:
            print(f"quickstart: stage `{argv[0]}` failed (exit {rc}); fix the error above and re-run "
                  "(finished stages are reused: the world is kept and training resumes)", file=sys.stderr)
            return rc
    minutes = (time.monotonic() - t0) / 60
    example = _write_example(world, out / "example")
    picture = _write_picture(world, out / "predictions", out / "side_by_side.png")
    print(f"""
quickstart finished in {minutes:.1f} min.
  synthetic world   {world}   (previews: {world / 'preview'})
  training run      {run_dir}   (log.jsonl, checkpoints/last.pt)
  evaluation        {out / 'eval.json'}
  picture           {picture}   (ground truth beside the prediction, first val keyframe)
  ONNX model        {onnx}

next:
  occflownet predict --model {onnx} --images {example} --calib {example / 'calib.json'} --out grid.npz --png bev.png
  occflownet serve --model {onnx} --port 8000""")
    return 0


def _write_picture(world, predictions, path):
    """The side-by-side picture (eval/picture.py) of the first val keyframe's saved prediction."""
    import numpy as np

    from occflownet.data.index import load_index
    from occflownet.eval.picture import sample_side_by_side
    from occflownet.pictures import save_png

    index = load_index(world)
    sample = index[int(index.split_positions("val")[0])]
    with np.load(predictions / f"{sample.token}.npz") as z:
        occupancy = z["occupancy"]
    return save_png(path, sample_side_by_side(world, sample, occupancy))


def _write_example(world, folder):
    """Copy the six images of the first val keyframe to ``folder/CAM_*.jpg`` with its ``calib.json``."""
    import json
    import shutil

    from occflownet.data.index import load_index

    index = load_index(world)
    sample = index[int(index.split_positions("val")[0])]
    folder.mkdir(parents=True, exist_ok=True)
    for cam in sample.cameras:
        shutil.copyfile(world / cam.path, folder / f"{cam.name}.jpg")
    cams = {c.name: {"intrinsic": c.intrinsic.tolist(), "cam2ego": c.sensor2ego.tolist()} for c in sample.cameras}
    (folder / "calib.json").write_text(json.dumps({"cameras": cams, "sample_token": sample.token}, indent=1))
    return folder
