"""`occflownet eval`: Occ3D mIoU (camera mask and all voxels, per class, static/dynamic) and RayIoU (1, 2, 4 m) of a
checkpoint or of an exported ONNX model on a split of a prepared root. JSON to stdout, a readable table to stderr.

The data is checked first (index present, split known, every sample labelled), then the model is loaded, then the
run starts. `--model` runs onnxruntime only and never imports torch."""
import sys

from occflownet.eval.evaluate import EvalConfig
from occflownet.options import add_options, config_kwargs

HELP = "evaluate a checkpoint or ONNX model (mIoU, RayIoU); JSON to stdout, table to stderr"


def add_arguments(p):
    """The model source, ``--dataroot``, the fields of EvalConfig (``occflownet/options.py``), ``--output`` and
    ``--quiet``."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="occflownet checkpoint (its weights are the EMA weights), run in torch")
    src.add_argument("--model", help="exported ONNX model, run by onnxruntime (no torch)")
    p.add_argument("--dataroot", required=True,
                   help="nuScenes-format root with Occ3D gts/, indexed by `occflownet prepare --dataroot DIR`")
    add_options(p, EvalConfig)
    p.add_argument("--output", default=None, metavar="FILE", help="also write the JSON result to FILE")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _message(exc: BaseException) -> str:
    # str(KeyError("x")) is "'x'": print the message itself
    return str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)


def run(args) -> int:
    from pathlib import Path

    from occflownet.data.tables import DatasetError
    from occflownet.eval import dumps_json, format_table
    from occflownet.eval.evaluate import evaluate, select_samples

    source = args.model or args.checkpoint
    cfg = EvalConfig(**config_kwargs(args, EvalConfig))
    if cfg.html and not cfg.save_predictions:
        print("occflownet eval: error: --html needs --save-predictions DIR (the viewer files go there)",
              file=sys.stderr)
        return 2
    try:
        if not Path(source).is_file():
            what = "ONNX model" if args.model else "checkpoint"
            raise FileNotFoundError(f"{what} not found: {source}")
        samples = select_samples(args.dataroot, cfg.version, cfg.split, cfg.max_samples)
        if args.model:
            from occflownet.runtime import OnnxPredictor

            predict = OnnxPredictor.open(args.model, cfg.threads)
        else:
            from occflownet.model import model_from_source
            from occflownet.runtime import TorchPredictor

            predict = TorchPredictor(model_from_source(args.checkpoint))
        result = evaluate(samples, predict, cfg, progress=not args.quiet)
        viewers = _write_viewers(samples, Path(cfg.save_predictions), cfg.html) if cfg.html else []
    except (DatasetError, FileNotFoundError, KeyError, ValueError, OSError) as e:
        print(f"occflownet eval: error: {_message(e)}", file=sys.stderr)
        return 1
    result = {"source": str(source), "source_kind": "onnx" if args.model else "checkpoint", **result}
    text = dumps_json(result)
    print(format_table(result), file=sys.stderr)
    print(text)
    if args.output:
        Path(args.output).write_text(text + "\n")
    for path in viewers:
        print(f"wrote {path}", file=sys.stderr)
    return 0


def _write_viewers(samples, folder, n: int) -> list:
    """The viewer files (ground truth beside prediction) of the first ``n`` samples, from their saved predictions."""
    import numpy as np

    from occflownet.eval.picture import sample_viewer

    paths = []
    for position in samples.positions[:n]:
        sample = samples.index[int(position)]
        with np.load(folder / f"{sample.token}.npz") as z:
            occupancy = z["occupancy"]
        paths.append(sample_viewer(samples.dataroot, sample, occupancy, folder / f"{sample.token}.html"))
    return paths
