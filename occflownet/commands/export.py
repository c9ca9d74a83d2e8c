"""`occflownet export`: export a model to ONNX (contract v1) with a torch ↔ onnxruntime parity check."""
import sys

from occflownet.choices import INT8_RANGES
from occflownet.commands.model_source import add_model_source, source_problem

HELP = "export a model to ONNX with parity check"


def add_arguments(parser):
    add_model_source(parser)
    parser.add_argument("--out", required=True, help="output .onnx file (written only if every check passes)")
    parser.add_argument("--parity-frame", action="append", default=[], metavar="DIR",
                        help="extra parity sample: a folder with six CAM_*.jpg and calib.json (repeatable)")
    parser.add_argument("--fp16", action="store_true", help="also write <out>.fp16.onnx (float16 weights/compute)")
    parser.add_argument("--int8", action="store_true",
                        help="also write <out>.int8.onnx (static QDQ quantisation, calibrated on synthetic samples)")
    parser.add_argument("--int8-range", choices=INT8_RANGES, default="reduced",
                        help="int8 weights: 7-bit, exact on every x86 CPU (reduced, the default) or 8-bit, for CPUs "
                             "with VNNI or AMX (full; on AVX2-only CPUs onnxruntime's kernels may saturate)")


def run(args) -> int:
    problem = source_problem(args)
    if problem:
        print(f"occflownet export: {problem}", file=sys.stderr)
        return 2
    from occflownet.export.onnx_export import ExportError, export_model
    from occflownet.model import CheckpointError, model_from_source

    try:
        model = model_from_source(args.checkpoint, args.preset, args.seed)
        result = export_model(model, model.cfg, args.out, parity_frames=args.parity_frame)
    except (ExportError, CheckpointError, FileNotFoundError, ValueError) as exc:
        print(f"occflownet export: {exc}", file=sys.stderr)
        return 1
    print(result.summary())
    if args.fp16 or args.int8:
        from occflownet.export.variants import write_variants

        try:
            frame = args.parity_frame[0] if args.parity_frame else None
            for line in write_variants(result.path, model.cfg, fp16=args.fp16, int8=args.int8, frame=frame,
                                       int8_range=args.int8_range):
                print(line)
        except (ExportError, ValueError, RuntimeError) as exc:
            print(f"occflownet export: variant failed: {exc}", file=sys.stderr)
            return 1
    return 0
