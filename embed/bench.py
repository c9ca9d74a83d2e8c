"""C++ (occflownet-run) against Python onnxruntime on the same model and frame, interleaved in one run.

    python embed/bench.py --model m.onnx [--images DIR] [--calib calib.json] [--runs 20] [--rounds 3] [--threads 2]

Both sides: the six JPEGs are read once; each timed run decodes them at the contract's reduced scale for the
model (``occflownet.contract.decode_reduction``; C++: libjpeg-turbo's DCT scaling into the input buffer; Python:
OpenCV imdecode IMREAD_REDUCED_COLOR_n + RGB + np.stack, as `occflownet predict`) and runs one inference with the same session
settings (intra-op threads, spinning off, all graph optimisations). Each round runs both sides, alternating which
goes first (C++ in a fresh process; one warm-up run each); p50s per round and the median over rounds are printed with the load average.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FRAME = REPO.parent / "shared" / "data" / "nuscenes-frame"


def python_round(model: Path, images_dir: Path, calib: Path, runs: int, threads: int) -> tuple[float, float]:
    from occflownet.contract import decode_reduction, image_header, load_calibration
    from occflownet.predict import decode_image, find_camera_images
    from occflownet.runtime import OnnxPredictor, frame_calibration

    predictor = OnnxPredictor.open(model, threads=threads)
    blobs = [(p.read_bytes(), str(p)) for p in find_camera_images(images_dir).values()]
    header = image_header(blobs[0][0])
    scale = decode_reduction(header, predictor.input_size)
    decode = lambda: np.stack([decode_image(b, n, scale) for b, n in blobs])  # noqa: E731
    frame = frame_calibration(load_calibration(calib), [(header.width, header.height)] * len(blobs),
                              reductions=[scale] * len(blobs))
    predictor(frame.inputs(decode()))  # warm-up
    total, infer = [], []
    for _ in range(runs):
        t0 = time.perf_counter()
        images = decode()
        t1 = time.perf_counter()
        predictor(frame.inputs(images))
        t2 = time.perf_counter()
        total.append((t2 - t0) * 1e3)
        infer.append((t2 - t1) * 1e3)
    return float(np.median(infer)), float(np.median(total))


def cpp_round(binary: Path, model: Path, images_dir: Path, calib: Path, runs: int, threads: int, out: Path):
    proc = subprocess.run([str(binary), "--model", str(model), "--images", str(images_dir), "--calib", str(calib),
                           "--out", str(out), "--runs", str(runs), "--threads", str(threads)],
                          capture_output=True, text=True, check=True)
    m = re.search(r"p50 inference: ([\d.]+) ms, p50 decode\+inference: ([\d.]+) ms", proc.stdout)
    return float(m[1]), float(m[2])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--images", type=Path, default=FRAME)
    ap.add_argument("--calib", type=Path, default=None)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--binary", type=Path, default=REPO / "embed" / "build" / "release" / "occflownet-run")
    a = ap.parse_args()
    calib = a.calib or a.images / "calib.json"
    out = Path("/tmp") / f"embed-bench-{os.getpid()}.npy"
    print(f"model {a.model}, frame {a.images}, {a.runs} runs x {a.rounds} rounds, {a.threads} intra-op threads, "
          f"load average {os.getloadavg()[0]:.2f} at start")
    rows = {"python": [], "c++": []}
    for r in range(a.rounds):
        sides = [("python", lambda: python_round(a.model, a.images, calib, a.runs, a.threads)),
                 ("c++", lambda: cpp_round(a.binary, a.model, a.images, calib, a.runs, a.threads, out))]
        for side, measure in sides if r % 2 == 0 else sides[::-1]:  # alternate which side goes first
            rows[side].append(measure())
        print(f"round {r + 1}: python p50 {rows['python'][-1][0]:.1f} / {rows['python'][-1][1]:.1f} ms, "
              f"c++ p50 {rows['c++'][-1][0]:.1f} / {rows['c++'][-1][1]:.1f} ms (inference / decode+inference)")
    out.unlink(missing_ok=True)
    print(f"load average {os.getloadavg()[0]:.2f} at end")
    print("| side | p50 inference (median of rounds) | p50 decode + inference | rounds (inference) |")
    print("|---|---|---|---|")
    for side, vals in rows.items():
        inf, tot = np.median([v[0] for v in vals]), np.median([v[1] for v in vals])
        print(f"| {side} | {inf:.1f} ms | {tot:.1f} ms | {', '.join(f'{v[0]:.1f}' for v in vals)} |")


if __name__ == "__main__":
    main()
