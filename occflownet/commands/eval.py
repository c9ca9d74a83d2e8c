"""`occflownet eval`: Occ3D mIoU (camera mask and all voxels, per class, static/dynamic) and RayIoU of a checkpoint
or of an exported ONNX model on a split of a prepared root. JSON to stdout, a readable table to stderr."""
import sys

HELP = "evaluate a checkpoint or ONNX model (mIoU, RayIoU); JSON to stdout, table to stderr"


def add_arguments(p):
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="occflownet checkpoint (EMA weights), run in torch")
    src.add_argument("--model", help="exported ONNX model, run by onnxruntime (no torch)")
    p.add_argument("--dataroot", required=True, help="nuScenes-format root with gts/ (run `occflownet prepare` first)")
    p.add_argument("--version", default=None)
    p.add_argument("--split", default="val")
    p.add_argument("--save-predictions", default=None, metavar="DIR",
                   help="write <sample_token>.npz (occupancy uint8, density float32) per sample")
    p.add_argument("--max-samples", type=int, default=None)
    p.add_argument("--no-rayiou", action="store_true", help="skip RayIoU")
    p.add_argument("--output", default=None, help="also write the JSON result to this file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from pathlib import Path

    from occflownet.data.tables import DatasetError
    from occflownet.eval import dumps_json, format_table
    from occflownet.evaluate import evaluate, onnx_predictor

    try:
        if args.model:
            predict = onnx_predictor(args.model)
        else:
            from occflownet.evaluate import checkpoint_predictor
            from occflownet.model.checkpoint import CheckpointError

            try:
                predict = checkpoint_predictor(args.checkpoint)
            except CheckpointError as e:
                raise ValueError(str(e)) from e
        result = evaluate(args.dataroot, predict, args.version, args.split, args.save_predictions,
                          args.max_samples, rayiou=not args.no_rayiou, progress=not args.quiet)
    except (DatasetError, FileNotFoundError, KeyError, ValueError) as e:
        print(f"occflownet eval: error: {e}", file=sys.stderr)
        return 1
    result["source"] = args.model or args.checkpoint
    text = dumps_json(result)
    print(format_table(result), file=sys.stderr)
    print(text)
    if args.output:
        Path(args.output).write_text(text + "\n")
    return 0
