"""Speed of `occflownet synth` at default settings: seconds per keyframe (6 images + LiDAR keyframe and sweeps +
geometric truth + files + the label pipeline's Occ3D gt).

    python -m benchmarks.perf.bench_synth [--scenes 1 --frames 6 --width 480 --height 270 --preview] [--jsonl PATH]

Prints wall-clock and CPU (process) seconds per keyframe for a whole `generate` run (tables and files included),
then a per-stage breakdown for one keyframe, each with the load average and the float32 matmul rate (appended to
``--jsonl``). CPU time is printed too because the machine may be shared.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time

import numpy as np

from benchmarks.harness import Results, add_jsonl_option
from occflownet.synth.camera import render_camera
from occflownet.synth.frame import SensorRig
from occflownet.synth.generate import DEFAULT_SWEEPS, generate
from occflownet.synth.layout import WorldConfig, build_world
from occflownet.synth.lidar import cast_lidar
from occflownet.synth.voxelize import voxelize


def stage_times(width: int, height: int, seed: int, repeats: int = 3) -> dict[str, float]:
    """Median seconds of each stage of one keyframe (geometry at one instant, all sensors)."""
    world = build_world(WorldConfig(), seed, 0, 6)
    rig = SensorRig.default(width, height)
    out: dict[str, list[float]] = {}

    def timed(name, fn):
        t = time.perf_counter()
        result = fn()
        out.setdefault(name, []).append(time.perf_counter() - t)
        return result

    for r in range(repeats):
        t = 0.5 * r
        boxes = timed("geometry (boxes at t)", lambda: world.boxes_at(t))
        ego = world.ego2global(t)
        timed("6 camera images", lambda: [render_camera(world, boxes, rig.intrinsics[c], ego @ rig.cam2ego[c],
                                                        width, height) for c in range(6)])
        timed("LiDAR sweep", lambda: cast_lidar(world, boxes, ego @ rig.lidar2ego, rig.lidar))
        timed("voxelise the truth", lambda: voxelize(world, boxes, ego))
    return {k: float(np.median(v)) for k, v in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sweeps", type=int, default=DEFAULT_SWEEPS)
    ap.add_argument("--preview", action="store_true")
    add_jsonl_option(ap)
    args = ap.parse_args(argv)
    results = Results("bench_synth", args.jsonl)
    n = args.scenes * args.frames
    with tempfile.TemporaryDirectory() as tmp:
        wall, cpu = time.perf_counter(), time.process_time()
        generate(tmp, scenes=args.scenes, frames=args.frames, seed=args.seed, width=args.width, height=args.height,
                 preview=args.preview, progress=False, sweeps=args.sweeps)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    results.add({"keyframes": n, "width": args.width, "height": args.height, "sweeps": args.sweeps,
                 "preview": args.preview, "wall_s_per_keyframe": wall / n, "cpu_s_per_keyframe": cpu / n},
                f"generate: {n} keyframes at {args.width}x{args.height}, {args.sweeps} sweeps between keyframes"
                f"{', with previews' if args.preview else ''}, labels included: {wall / n:.3f} s/keyframe wall, "
                f"{cpu / n:.3f} s/keyframe CPU (the labels alone: benchmarks/studies/labels_stats.py)")
    stages = stage_times(args.width, args.height, args.seed)
    results.add({"stage_seconds": stages}, "one keyframe by stage (median of 3):\n"
                + "\n".join(f"  {name:24s} {sec:.3f} s" for name, sec in stages.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
