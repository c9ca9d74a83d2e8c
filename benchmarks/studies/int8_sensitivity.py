"""Per-layer int8 sensitivity of an exported fp32 graph: what quantising each node that today's int8 variant keeps
in float32 would cost in agreement with fp32.

    python -m benchmarks.studies.int8_sensitivity --onnx M.onnx --out DIR [--frame DIR] [--int8-range reduced|full]

Today's int8 variant (``export/variants.py``: the image convolutions in int8; the 3D decoder's convolutions, the
per-voxel Gemms and the image resampling MatMuls in float32) is the first row. Then each decoder convolution and
each Gemm is quantised on its own, on top of today's variant, then all decoder convolutions, then every
convolution and Gemm. Each graph is calibrated as the variant is (the frame's variations) and compared with the
fp32 graph on the frame as the inference paths decode it: occupancy voxels equal, occupied voxels whose class
changed (of the fp32 occupied ones), density max |Δ|. The equal fraction counts every voxel, free ones included;
the occupied-voxel figure is the stricter one. One JSON line per graph is appended to ``OUT/sensitivity.jsonl`` as
it comes. Speed is not measured here: ``python -m benchmarks.perf.bench_inference --profile`` gives each node's kernel time.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import onnx

from benchmarks.harness import SHARED_DATA, append_jsonl

FRAME = SHARED_DATA / "nuscenes-frame"


def main(argv=None) -> int:
    from occflownet.choices import INT8_RANGES
    from occflownet.contract import parse_metadata
    from occflownet.export.onnx_export import agreement
    from occflownet.export.parity import inference_frame_sample
    from occflownet.export.variants import INT8_OP_TYPES, activation_matmuls, float_in_int8, voxel_convs, write_int8
    from occflownet.model.presets import get_preset
    from occflownet.occ3d import FREE
    from occflownet.runtime import OnnxPredictor

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--onnx", required=True, help="an fp32 graph written by `occflownet export` (a trained model)")
    p.add_argument("--out", required=True, help="folder for the variants and sensitivity.jsonl")
    p.add_argument("--frame", default=str(FRAME), help="real frame folder (calibration and agreement)")
    p.add_argument("--int8-range", choices=INT8_RANGES, default="reduced",
                   help="int8 weights, as `occflownet export --int8-range`")
    args = p.parse_args(argv)

    src, out = Path(args.onnx), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    proto = onnx.load(str(src))
    meta = parse_metadata({q.key: q.value for q in proto.metadata_props}, str(src))
    cfg = get_preset(meta.preset, input_size=tuple(meta.input_size))
    today = float_in_int8(proto)
    matmuls, decoder = activation_matmuls(proto), voxel_convs(proto)
    gemms = [n.name for n in proto.graph.node if n.op_type == "Gemm"]
    sample = inference_frame_sample(args.frame, cfg)
    ref_occ, ref_density = OnnxPredictor.open(src)(sample.inputs)
    occupied = ref_occ != FREE
    print(f"{src}: preset {meta.preset}, fp32 occupies {100 * occupied.mean():.2f} % of the voxels on {sample.name}; "
          f"decoder convolutions {decoder}; Gemms {gemms}", flush=True)

    with_gemms = [*INT8_OP_TYPES, "Gemm"]
    rows = [("today's int8 variant", today, INT8_OP_TYPES)]
    rows += [(f"+ decoder conv {n}", [k for k in today if k != n], INT8_OP_TYPES) for n in decoder]
    rows += [(f"+ Gemm {n}", today + [g for g in gemms if g != n], with_gemms) for n in gemms]
    rows += [("+ every decoder conv", matmuls, INT8_OP_TYPES),
             ("+ every decoder conv and Gemm", matmuls, with_gemms)]
    for i, (label, keep, ops) in enumerate(rows):
        t = time.perf_counter()
        dst = write_int8(src, out / f"sensitivity-{i}.onnx", cfg, frame=args.frame, int8_range=args.int8_range,
                         keep_float=keep, op_types=ops)
        occ, density = OnnxPredictor.open(dst)(sample.inputs)
        a = agreement(ref_occ, ref_density, occ, density)
        line = {"graph": label, "voxels_equal_pct": round(100 * a["occupancy_equal_fraction"], 4),
                "occupied_changed_pct": round(100 * float(np.mean(occ[occupied] != ref_occ[occupied])), 2),
                "occupied_pct": round(100 * float(np.mean(occ != FREE)), 3),
                "density_max_abs_diff": round(a["density_max_abs_diff"], 4), "seconds": round(time.perf_counter() - t)}
        print(json.dumps(line), flush=True)
        append_jsonl(out / "sensitivity.jsonl", line)
        dst.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
