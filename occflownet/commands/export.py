"""`occflownet export`: export a model to ONNX (contract v1) with a torch ↔ onnxruntime parity check.

The options are the model source (``commands/model_source.py``), ``--out``, ``--parity-frame`` and the fields of
:class:`occflownet.export.config.ExportConfig` (``occflownet/options.py``)."""
import sys

from occflownet.commands.model_source import add_model_source, source_problem
from occflownet.export.config import ExportConfig
from occflownet.options import add_options, config_kwargs

HELP = "export a model to ONNX with parity check"


def add_arguments(parser):
    add_model_source(parser)
    parser.add_argument("--out", required=True, help="output .onnx file (written only if every check passes)")
    parser.add_argument("--parity-frame", action="append", default=[], metavar="DIR",
                        help="extra parity sample: a folder with six CAM_*.jpg and calib.json (repeatable)")
    add_options(parser, ExportConfig)


def run(args) -> int:
    problem = source_problem(args)
    if problem:
        print(f"occflownet export: {problem}", file=sys.stderr)
        return 2
    from occflownet.export.onnx_export import ExportError, export_model
    from occflownet.model import CheckpointError, model_from_source

    cfg = ExportConfig(**config_kwargs(args, ExportConfig))
    try:
        model = model_from_source(args.checkpoint, args.preset, args.seed)
        result = export_model(model, model.cfg, args.out, parity_frames=args.parity_frame)
    except (ExportError, CheckpointError, FileNotFoundError, ValueError) as exc:
        print(f"occflownet export: {exc}", file=sys.stderr)
        return 1
    print(result.summary())
    if cfg.fp16 or cfg.int8:
        from occflownet.export.variants import write_variants

        try:
            frame = args.parity_frame[0] if args.parity_frame else None
            for line in write_variants(result.path, model.cfg, fp16=cfg.fp16, int8=cfg.int8, frame=frame,
                                       int8_range=cfg.int8_range):
                print(line)
        except (ExportError, ValueError, RuntimeError) as exc:
            print(f"occflownet export: variant failed: {exc}", file=sys.stderr)
            return 1
    return 0
