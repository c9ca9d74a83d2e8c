"""Cost of the in-graph antialiased resize: the explicit triangle filter (``occflownet.model.preprocess``) against
the fused kernels it replaced (torch ``F.interpolate(antialias=True)``, ONNX ``Resize(antialias=1)``).

    python -m benchmarks.perf.bench_preprocess [--runs 40] [--threads 2] [--jsonl PATH]

Prints, interleaving the two variants run by run (``benchmarks.harness.interleaved``, after one untimed run of
each; so machine load hits both alike), each row with the load average and the float32 matmul rate (appended to
``--jsonl``):
- onnxruntime: the whole preprocessing graph (crop, decimation, resize, normalisation, intrinsics) exported both ways,
  on six images of the real frame (1600x900, when ``../shared/data/nuscenes-frame`` exists, else random) and on the
  same images shrunk to 480x270;
- torch eager: the resize alone on six images as preprocessing sees them (3x445x800 for 1600x900, 3x267x480);
- how far apart the two are (0..255 scale).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import SHARED_DATA, Results, add_jsonl_option, interleaved

FRAME = SHARED_DATA / "nuscenes-frame"


def _graphs(tmp: Path, images: np.ndarray, K: np.ndarray) -> dict[str, Path]:
    import torch
    import torch.nn.functional as F

    from occflownet.export.onnx_export import trace_to_onnx
    from occflownet.model import preprocess
    from occflownet.model.presets import IMAGENET_MEAN, IMAGENET_STD

    class Pre(torch.nn.Module):
        def __init__(self, fused: bool):
            super().__init__()
            self.fused = fused

        def forward(self, images, intrinsics):
            if not self.fused:
                return preprocess.preprocess_images(images, intrinsics, (160, 288), IMAGENET_MEAN, IMAGENET_STD)
            saved = preprocess.antialiased_resize
            preprocess.antialiased_resize = lambda x, size: F.interpolate(
                x, size=size, mode="bilinear", align_corners=False, antialias=True)
            try:
                return preprocess.preprocess_images(images, intrinsics, (160, 288), IMAGENET_MEAN, IMAGENET_STD)
            finally:
                preprocess.antialiased_resize = saved

    b = torch.export.Dim("batch", min=1, max=64)
    h, w = torch.export.Dim("h", min=32, max=16384), torch.export.Dim("w", min=32, max=16384)
    inputs = (torch.from_numpy(images).repeat(2, 1, 1, 1, 1), torch.from_numpy(K).repeat(2, 1, 1, 1))
    out = {}
    for name, fused in (("Resize(antialias=1)", True), ("triangle filter", False)):
        path = tmp / f"{'fused' if fused else 'filter'}.onnx"
        trace_to_onnx(Pre(fused), inputs, path, ["images", "intrinsics"], ["x", "k"],
                      {"images": {0: b, 2: h, 3: w}, "intrinsics": {0: b}})
        out[name] = path
    return out


def _interleaved(fns: dict, runs: int) -> dict[str, list[float]]:
    """{variant: ms per run} of ``runs`` interleaved runs after one untimed run of each."""
    for f in fns.values():
        f()
    return {k: [1000 * seconds for seconds, _ in v] for k, v in interleaved(fns, runs).items()}


def _add(results: Results, label: str, times: dict[str, list[float]], apart: float) -> None:
    line = f"{label:<34}" + "  ".join(f"{k}: p50 {np.median(v):6.1f} ms (min {min(v):6.1f})" for k, v in times.items())
    results.add({"what": label, "p50_ms": {k: float(np.median(v)) for k, v in times.items()},
                 "min_ms": {k: min(v) for k, v in times.items()}, "max_abs_diff_of_255": apart},
                line + f"  max |diff| {apart:.1e}/255")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    add_jsonl_option(ap)
    args = ap.parse_args()
    results = Results("bench_preprocess", args.jsonl)

    import cv2
    import onnxruntime as ort
    import torch
    import torch.nn.functional as F

    from occflownet.model.preprocess import antialiased_resize

    torch.set_num_threads(args.threads)
    if (FRAME / "CAM_FRONT.jpg").is_file():
        from occflownet.predict import load_image_folder

        full = load_image_folder(FRAME)[None]
        source = "real frame"
    else:
        full = np.random.default_rng(0).integers(0, 256, (1, 6, 900, 1600, 3), dtype=np.uint8)
        source = "random images"
    small = np.stack([cv2.resize(a, (480, 270), interpolation=cv2.INTER_AREA) for a in full[0]])[None]
    K = np.tile(np.eye(3, dtype=np.float32), (1, 6, 1, 1))
    print(f"{source}; {args.threads} threads; {args.runs} interleaved runs")
    with tempfile.TemporaryDirectory() as tmp:
        graphs = _graphs(Path(tmp), full, K)
        so = ort.SessionOptions()
        so.intra_op_num_threads = args.threads
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        sessions = {k: ort.InferenceSession(str(p), so, providers=["CPUExecutionProvider"]) for k, p in graphs.items()}
        for label, x in (("ORT preprocessing, 6x1600x900", full), ("ORT preprocessing, 6x480x270", small)):
            feeds = {"images": x, "intrinsics": K}
            outs = [s.run(None, feeds)[0] for s in sessions.values()]
            std = np.array([58.395, 57.12, 57.375], np.float32).reshape(1, 3, 1, 1)
            apart = float(np.abs((outs[0] - outs[1]) * std).max())
            _add(results, label, _interleaved({k: (lambda s=s: s.run(None, feeds)) for k, s in sessions.items()},
                                              args.runs), apart)
    for shape in ((6, 3, 445, 800), (6, 3, 267, 480)):
        x = torch.randint(0, 256, shape, generator=torch.Generator().manual_seed(0)).float()
        fns = {"F.interpolate(antialias)": lambda: F.interpolate(x, size=(160, 288), mode="bilinear",
                                                                 align_corners=False, antialias=True),
               "triangle filter": lambda: antialiased_resize(x, (160, 288))}
        with torch.no_grad():
            apart = float((fns["F.interpolate(antialias)"]() - fns["triangle filter"]()).abs().max())
            _add(results, f"torch resize, {'x'.join(map(str, shape))}", _interleaved(fns, args.runs), apart)
    return 0


if __name__ == "__main__":
    sys.exit(main())
