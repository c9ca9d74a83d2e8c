"""`occflownet predict`: predict occupancy for one set of six images.

``--model model.onnx`` runs onnxruntime only (torch is never imported); ``--checkpoint`` and
``--preset P --random-init --seed N`` run the torch model.
"""
import sys

from occflownet.commands.model_source import add_model_source, source_problem

HELP = "predict occupancy for one set of six images"


def add_arguments(parser):
    add_model_source(parser, onnx=True)
    parser.add_argument("--images", required=True, help="folder with CAM_FRONT.jpg ... CAM_BACK_RIGHT.jpg")
    parser.add_argument("--calib", required=True, help="calibration JSON (per camera intrinsic + cam2ego)")
    parser.add_argument("--out", required=True, help="output .npz (occupancy uint8, density float32)")
    parser.add_argument("--png", help="optional top-down picture of the grid")
    parser.add_argument("--html", help="optional 3D viewer of the grid (one self-contained HTML file, with the "
                                       "camera images and frusta)")
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: cores)")


def run(args) -> int:
    import time

    from occflownet import contract, pictures, predict, viewer
    from occflownet.occ3d import CLASS_NAMES, FREE
    from occflownet.runtime import OnnxPredictor, TorchPredictor

    problem = source_problem(args)
    if problem:
        print(f"occflownet predict: {problem}", file=sys.stderr)
        return 2
    try:
        if args.model:
            predictor = OnnxPredictor.open(args.model, args.threads)
        else:
            from occflownet.model import model_from_source

            predictor = TorchPredictor(model_from_source(args.checkpoint, args.preset, args.seed))
        frame = predict.load_frame(args.images, predictor.input_size)   # JPEGs at reduced scale (docs/contracts.md)
        calib = contract.load_calibration(args.calib)
        inputs = frame.inputs(calib)
        t0 = time.perf_counter()
        occupancy, density = (batch[0] for batch in predictor(inputs))      # the one frame of the batch
        seconds = time.perf_counter() - t0
        predict.save_grid(args.out, occupancy, density)
        if args.png:
            pictures.save_png(args.png, pictures.top_down(occupancy))
        if args.html:
            files = {cam: p.read_bytes() for cam, p in predict.find_camera_images(args.images).items()}
            viewer.write_viewer(args.html, [viewer.ViewGrid("prediction", occupancy)], calib, files,
                                title=f"occflownet predict: {args.images}", subtitle=f"grid: {args.out}")
    except (FileNotFoundError, ValueError, OSError) as exc:
        print(f"occflownet predict: {exc}", file=sys.stderr)
        return 1
    counts = predict.class_counts(occupancy)
    occupied = sum(n for c, n in counts.items() if c != FREE)
    top = sorted(((n, c) for c, n in counts.items() if c != FREE and n), reverse=True)[:5]
    print(f"wrote {args.out}: {occupied} occupied voxels of {occupancy.size} ({seconds * 1000:.0f} ms); "
          f"top classes: " + ", ".join(f"{CLASS_NAMES[c]} {n}" for n, c in top))
    for extra in (args.png, args.html):
        if extra:
            print(f"wrote {extra}")
    return 0
