"""What the JPEG decoding scale changes: one exported model's occupancy on a real frame fed whole and at each
reduced scale libjpeg decodes to, and what decoding and inference cost at each.

    python -m benchmarks.studies.decode_scale --onnx M.onnx [--frame DIR] [--runs 15] [--threads 2]

For each n of 1, 2, 4, 8 whose decoded image still holds the model's input window
(``occflownet.contract.holding_reductions``; the contract's own n, ``decode_reduction``, marked), the six JPEGs of
the frame are decoded at 1/n, fed with the intrinsics of the pixel-centre rule (``occflownet.runtime.frame_inputs``)
and run through onnxruntime. Printed per scale: decoded size, decoding time of the six in parallel threads (as
``predict.load_frame`` decodes them) and inference time (p50 of ``--runs`` rounds, the two interleaved after one
warm-up: ``benchmarks.harness.interleaved``), occupied voxels; then for each pair of scales the voxels equal, the
IoU of the occupied voxels and density max |Δ|. Use a trained model: random weights have no structure to keep.
"""
from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from itertools import combinations
from pathlib import Path

import numpy as np

from benchmarks.harness import SHARED_DATA, interleaved
from occflownet.occ3d import FREE

FRAME = SHARED_DATA / "nuscenes-frame"


def compare(a, b) -> str:
    """Voxels equal, occupied-voxel IoU and density max |Δ| of two (occupancy, density) outputs."""
    oa, ob = a[0] != FREE, b[0] != FREE
    iou = np.sum(oa & ob) / max(1, np.sum(oa | ob))
    return (f"voxels equal {100 * np.mean(a[0] == b[0]):.3f} %, occupied IoU {100 * iou:.2f} %, "
            f"density max |d| {np.abs(a[1] - b[1]).max():.3f}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--onnx", required=True, help="an exported model (contract v1)")
    p.add_argument("--frame", default=str(FRAME), help="a folder of six camera JPEGs and calib.json")
    p.add_argument("--runs", type=int, default=15)
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    args = p.parse_args(argv)

    from occflownet.contract import decode_reduction, holding_reductions, image_header, load_calibration
    from occflownet.predict import decode_image, find_camera_images
    from occflownet.runtime import OnnxPredictor, frame_inputs

    frame = Path(args.frame)
    files = list(find_camera_images(frame).values())
    if any(f.suffix.lower() not in (".jpg", ".jpeg") for f in files):
        print(f"{frame}: the six camera images must be JPEGs", file=sys.stderr)
        return 1
    blobs = [f.read_bytes() for f in files]
    header = image_header(blobs[0])
    calib = load_calibration(frame / "calib.json")
    predictor = OnnxPredictor.open(args.onnx, args.threads)
    contract_n = decode_reduction(header, predictor.input_size)
    pool = ThreadPoolExecutor(len(blobs))
    outputs = {}
    for n in holding_reductions(header.width, header.height, predictor.input_size):
        decode = lambda n=n: np.stack(list(pool.map(lambda b: decode_image(b, "image", n), blobs)))  # noqa: E731
        images = decode()
        inputs = frame_inputs(images, calib, sizes=[(header.width, header.height)] * len(blobs),
                              reductions=[n] * len(blobs))
        outputs[n] = predictor(inputs)                                             # also the warm-up
        walls = interleaved({"decode": decode, "inference": lambda: predictor(inputs)}, args.runs)
        t_decode, t_infer = (float(np.median([t for t, _ in walls[side]])) for side in ("decode", "inference"))
        mark = "  <- the contract's scale for this model" if n == contract_n else ""
        print(f"1/{n}: {images.shape[2]}x{images.shape[1]}, decode p50 {1e3 * t_decode:.1f} ms, inference p50 "
              f"{1e3 * t_infer:.1f} ms, occupied {100 * np.mean(outputs[n][0] != FREE):.2f} % of voxels{mark}",
              flush=True)
    for a, b in combinations(sorted(outputs), 2):
        print(f"1/{a} against 1/{b}: {compare(outputs[a], outputs[b])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
