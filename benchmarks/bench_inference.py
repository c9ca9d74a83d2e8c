"""Inference latency per preset: torch eager vs onnxruntime (CPU), six native 1600x900 uint8 images → grid.

    python benchmarks/bench_inference.py [--presets tiny base] [--runs 20] [--occupied 0.25] [--variants]

For each preset a random-init model (seed 0) is exported (parity-checked on the real frame), then torch eager
(``model.inference``, torch threads = cores) and onnxruntime (CPU provider, intra-op threads = cores) run the same
six decoded images alternately, so both see the same machine load. Φσ's output bias is shifted so that a fraction
``--occupied`` of the voxels is occupied (Φs only runs on those; a random-init model would leave the grid empty
and flatter the timings). Printed: p50/p90 per backend, their ratio, model GFLOP (torch FLOP counter: matmuls and
convolutions) and the achieved GFLOP/s next to a 2048³ fp32 matmul measured in the same run. JPEG decoding is
timed separately and not included. ``--variants`` also writes the fp16 and int8 graphs and times them (with
their agreement with fp32 on the same images).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
FRAME = ROOT.parent / "shared" / "data" / "nuscenes-frame"
SPINNING = False  # onnxruntime worker threads busy-wait (--ort-spinning) or sleep (default, as in predict/serve)


def load_inputs():
    from occflownet.contract import calibration_arrays, load_calibration
    from occflownet.predict import load_image_folder
    from occflownet.rig import default_rig

    if (FRAME / "calib.json").is_file():
        t = time.perf_counter()
        images = load_image_folder(FRAME)
        decode_ms = (time.perf_counter() - t) * 1000
        K, T = calibration_arrays(load_calibration(FRAME / "calib.json"), 1600, 900)
        return images, K, T, decode_ms, "real nuScenes frame"
    K, T = calibration_arrays(default_rig(1600, 900))
    images = np.random.default_rng(0).integers(0, 256, (6, 900, 1600, 3), dtype=np.uint8)
    return images, K, T, float("nan"), "random images (real frame not found)"


def matmul_gflops(n: int = 2048, reps: int = 5) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    best = min(_timed(lambda: torch.mm(a, b)) for _ in range(reps))
    return 2 * n ** 3 / best / 1e9


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def model_flops(model, args) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model.inference(*args)
    return float(counter.get_total_flops())


def bench_preset(name: str, runs: int, occupied: float, images, K, T, workdir: Path, variants: bool) -> dict:
    from occflownet.export.onnx_export import export_model
    from occflownet.export.parity import ParitySample
    from occflownet.contract import create_session, run_session
    from occflownet.model import create_model, get_preset

    model = create_model(get_preset(name), seed=0).eval()
    args = (torch.from_numpy(images)[None], torch.from_numpy(K)[None], torch.from_numpy(T)[None])
    with torch.no_grad():
        logits = torch.logit(model.inference(*args)[1]).flatten()
        cut = torch.quantile(logits[::7], 1.0 - occupied) if occupied > 0 else logits.max() + 1
        model.decoder.sigma_head[-1].bias += torch.logit(torch.tensor(model.cfg.threshold)) - cut
        model.decoder.semantic_head[-1].bias.zero_()
    sample = ParitySample("bench", images[None], K[None], T[None])
    t = time.perf_counter()
    path = export_model(model, model.cfg, workdir / f"{name}.onnx", parity_samples=[sample]).path
    export_s = time.perf_counter() - t
    session = create_session(path, os.cpu_count(), spinning=SPINNING)
    flops = model_flops(model, args)
    torch_t, ort_t = [], []
    with torch.no_grad():
        for i in range(runs + 2):                                  # 2 warm-up rounds, alternating backends
            tt = _timed(lambda: model.inference(*args))
            to = _timed(lambda: run_session(session, images, K, T))
            if i >= 2:
                torch_t.append(tt)
                ort_t.append(to)
        occ, dens = run_session(session, images, K, T)
    extra = {}
    if variants:
        from occflownet.export.onnx_export import agreement
        from occflownet.export.variants import write_fp16, write_int8

        for tag, path_v in (("fp16", write_fp16(path, workdir / f"{name}.fp16.onnx")),
                            ("int8", write_int8(path, workdir / f"{name}.int8.onnx", model.cfg))):
            s_v = create_session(path_v, os.cpu_count(), spinning=SPINNING)
            run_session(s_v, images, K, T)
            times = [_timed(lambda: run_session(s_v, images, K, T)) for _ in range(max(3, runs // 2))]
            a = agreement(occ, dens, *run_session(s_v, images, K, T))
            extra[tag] = (float(np.median(times)), a)
    return {"variants": extra, "preset": name, "torch_p50": np.median(torch_t), "torch_p90": np.percentile(torch_t, 90),
            "ort_p50": np.median(ort_t), "ort_p90": np.percentile(ort_t, 90), "gflop": flops / 1e9,
            "occupied": float(np.mean(occ != 17)), "export_s": export_s}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    from occflownet.choices import PRESET_NAMES

    p.add_argument("--presets", nargs="+", default=["tiny", "base"], choices=PRESET_NAMES)
    p.add_argument("--runs", type=int, default=20, help="timed runs per backend (after 2 warm-up runs)")
    p.add_argument("--occupied", type=float, default=0.25, help="fraction of occupied voxels to simulate")
    p.add_argument("--variants", action="store_true", help="also time the fp16 and int8 graphs")
    p.add_argument("--ort-spinning", action="store_true", help="let onnxruntime's idle threads busy-wait")
    args = p.parse_args(argv)
    global SPINNING
    SPINNING = args.ort_spinning
    cores = os.cpu_count() or 1
    torch.set_num_threads(cores)
    images, K, T, decode_ms, source = load_inputs()
    print(f"inputs: {source}, 6x{images.shape[2]}x{images.shape[1]} uint8; JPEG decode of the six files "
          f"{decode_ms:.0f} ms (not included below)")
    print(f"threads: torch {torch.get_num_threads()}, onnxruntime {cores} (spinning {SPINNING}); load average "
          f"{os.getloadavg()[0]:.2f} at start")
    peak = matmul_gflops()
    print(f"fp32 matmul 2048^3 (torch): {peak:.1f} GFLOP/s")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.presets:
            runs = args.runs if name == "tiny" else max(3, args.runs // 4)
            r = bench_preset(name, runs, args.occupied, images, K, T, Path(tmp), args.variants)
            rows.append(r)
            print(f"{name}: torch eager p50 {r['torch_p50'] * 1e3:.1f} ms p90 {r['torch_p90'] * 1e3:.1f} ms | "
                  f"onnxruntime p50 {r['ort_p50'] * 1e3:.1f} ms p90 {r['ort_p90'] * 1e3:.1f} ms | "
                  f"torch/ort {r['torch_p50'] / r['ort_p50']:.2f}x | {r['gflop']:.1f} GFLOP -> "
                  f"torch {r['gflop'] / r['torch_p50']:.1f} GFLOP/s, ort {r['gflop'] / r['ort_p50']:.1f} GFLOP/s "
                  f"({100 * r['gflop'] / r['ort_p50'] / peak:.0f}% of matmul) | occupied "
                  f"{100 * r['occupied']:.0f}% | export {r['export_s']:.0f} s", flush=True)
            for tag, (p50, a) in r["variants"].items():
                print(f"  {name} {tag}: onnxruntime p50 {p50 * 1e3:.1f} ms; vs fp32: occupancy equal "
                      f"{100 * a['occupancy_equal_fraction']:.2f}% of voxels, density max abs diff "
                      f"{a['density_max_abs_diff']:.3f}", flush=True)
    print(f"load average at end {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
