"""Occupancy-flow figures: warp time per frame, voxels_in_box time, disk bytes per keyframe.

    python -m benchmarks.perf.bench_flow [--boxes 20] [--frames 6] [--repeat 7] [--device cpu] [--threads N]
        [--jsonl PATH]

A typical nuScenes keyframe has ~20 dynamic boxes in the grid range (cars dominate); the scene here has 14 cars,
3 pedestrians, 2 trucks and a bus, each filled with predicted voxels of its class, moved into 6 temporal frames
(t = ±1..±3) at a few m/s. Prints best-of-``--repeat`` times (the machine may be shared), each with the load
average and the float32 matmul rate (appended to ``--jsonl``): ``box_flows`` per keyframe, ``voxels_in_box`` per
box, ``flow_moves`` per sample, the plain per-frame copies, the warp per frame for each mover (forward, and forward
+ backward), and the bytes on disk per keyframe.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import Results, add_jsonl_option
from occflownet.choices import FLOW_MOVERS
from occflownet.occ3d import GRID, NUM_CLASSES
from occflownet.data.flow import box_flows, flow_moves, save_flow_records
from occflownet.geometry import make_transform, matrix_to_quaternion, yaw_to_quaternion
from occflownet.data.box_voxels import voxels_in_box
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes

KINDS = [(4, [1.9, 4.6, 1.7])] * 14 + [(7, [0.7, 0.8, 1.8])] * 3 + [(10, [2.6, 8.0, 3.2])] * 2 + [(3, [2.9, 11.5, 3.5])]


def make_tracks(n_boxes: int, frames, rng):
    """Global boxes per frame for a keyframe (ego at the origin, slightly yawed), plus the ego pose."""
    ego = make_transform(yaw_to_quaternion(0.3), [500.0, 800.0, 0.0])
    kinds = [KINDS[i % len(KINDS)] for i in range(n_boxes)]
    centre = rng.uniform([-32, -32, 0.2], [32, 32, 1.5], size=(n_boxes, 3))
    yaw = rng.uniform(-np.pi, np.pi, n_boxes)
    speed = rng.uniform(0, 6, n_boxes)  # m/s, keyframes 0.5 s apart
    boxes = {}
    for t in [0, *frames]:
        rows = {"instance_token": [], "label": [], "center": [], "size_wlh": [], "rotation": []}
        for b, (cls, wlh) in enumerate(kinds):
            if t != 0 and rng.random() < 0.1:  # ~10 % of the boxes are missing at some t
                continue
            c = centre[b] + 0.5 * t * speed[b] * np.array([np.cos(yaw[b]), np.sin(yaw[b]), 0.0])
            pose = ego @ make_transform(yaw_to_quaternion(yaw[b] + 0.02 * t), c)
            rows["instance_token"].append(f"inst{b}")
            rows["label"].append(cls)
            rows["center"].append(pose[:3, 3])
            rows["size_wlh"].append(wlh)
            rows["rotation"].append(matrix_to_quaternion(pose[:3, :3]))
        boxes[t] = {k: np.asarray(v) for k, v in rows.items()}
    return boxes, ego


def timed(fn, repeat):
    """Best of ``repeat`` runs after a warm-up: on a shared machine the minimum is the least disturbed figure."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.min(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=int, default=20)
    ap.add_argument("--frames", type=int, default=6, help="temporal frames per keyframe (t = ±1..±frames/2)")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave the default)")
    add_jsonl_option(ap)
    args = ap.parse_args()
    results = Results("bench_flow", args.jsonl)
    if args.threads:
        torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    half = args.frames // 2
    frames = [t for t in range(-half, half + 1) if t != 0]
    boxes, ego = make_tracks(args.boxes, frames, rng)
    record = box_flows("bench", boxes[0], {t: boxes[t] for t in frames}, ego)
    arrays = bench_precompute(record, boxes, ego, frames, args, results)
    bench_warp(record, arrays, frames, args, results)
    bench_disk(record, frames, rng, args, results)


def bench_precompute(record, boxes, ego, frames, args, results: Results) -> dict:
    """box_flows once per keyframe (prepare); voxels_in_box per box and flow_moves per sample (data workers).
    Returns the flow_moves arrays."""
    t_prep = timed(lambda: box_flows("bench", boxes[0], {t: boxes[t] for t in frames}, ego), args.repeat)
    print(f"device={args.device} threads={torch.get_num_threads()} boxes={len(record.box_index)} "
          f"moves={len(record.offset)} frames={frames}")
    results.add({"box_flows_ms_per_keyframe": 1e3 * t_prep},
                f"box_flows (precompute, once per keyframe in prepare): {1e3 * t_prep:.2f} ms/keyframe")
    t_box = timed(lambda: [voxels_in_box(c, s, q) for c, s, q in zip(record.center, record.size_wlh,
                                                                         record.rotation)], args.repeat)
    t_moves = timed(lambda: flow_moves(record, frames), args.repeat)
    arrays = flow_moves(record, frames)
    results.add({"voxels_in_box_ms_per_box": 1e3 * t_box / len(record.box_index),
                 "flow_moves_ms_per_sample": 1e3 * t_moves, "voxels_listed": len(arrays["voxels"])},
                f"voxels_in_box: {1e3 * t_box / len(record.box_index):.3f} ms/box; flow_moves (all boxes, "
                f"{len(frames)} frames): {1e3 * t_moves:.2f} ms/sample; voxels listed: {len(arrays['voxels'])}")
    return arrays


def bench_warp(record, arrays, frames, args, results: Results) -> None:
    """warp_volumes forward (and forward + backward) per frame for both movers, against plain copies."""
    # a prediction where every box's body is predicted as its class
    density = torch.rand(1, *GRID.shape) * 0.2
    logits = torch.randn(1, *GRID.shape, NUM_CLASSES)
    for c, s, q, cls in zip(record.center, record.size_wlh, record.rotation, record.label):
        body = torch.as_tensor(voxels_in_box(c, s, q, margin_scale=1.0, margin_add=0.0))
        density[0][tuple(body.T)] = 0.9
        logits[0][tuple(body.T) + (int(cls),)] = 8.0
    density, logits = density.to(args.device), logits.to(args.device)
    moves = PackedMoves.from_arrays(**arrays).to(args.device)
    source = torch.zeros(len(frames), dtype=torch.long, device=args.device)
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    no_moves = PackedMoves.from_arrays(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0))

    def copy_only():  # the same call with no boxes: the per-frame copies every temporal frame needs anyway
        out = warp_volumes(density, logits, source, no_moves)
        sync()
        return out

    t_copy = timed(copy_only, args.repeat)
    results.add({"copy_ms_per_frame": 1e3 * t_copy / len(frames)},
                f"plain copies (no boxes) of {len(frames)} frames: {1e3 * t_copy / len(frames):.1f} ms/frame")
    for mover in FLOW_MOVERS:
        def run():
            out = warp_volumes(density, logits, source, moves, mover)
            sync()
            return out

        t_fwd = timed(run, args.repeat)
        d = density.clone().requires_grad_()
        l_ = logits.clone().requires_grad_()

        def run_bwd():
            out_d, out_l = warp_volumes(d, l_, source, moves, mover)
            (out_d.sum() + out_l.sum()).backward()
            sync()

        t_bwd = timed(run_bwd, args.repeat)
        results.add({"mover": mover, "forward_ms_per_frame": 1e3 * t_fwd / len(frames),
                     "forward_backward_ms_per_frame": 1e3 * t_bwd / len(frames)},
                    f"warp {mover:7s}: forward {1e3 * t_fwd / len(frames):.1f} ms/frame "
                    f"(moves only ≈ {1e3 * (t_fwd - t_copy) / len(frames):.1f} ms/frame), forward+backward "
                    f"{1e3 * t_bwd / len(frames):.1f} ms/frame")


def bench_disk(record, frames, rng, args, results: Results) -> None:
    """Bytes on disk: one record in its own file, and 200 keyframes in one file."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "one.npz"
        save_flow_records(path, [record])
        single = path.stat().st_size
        many = []
        for n in range(200):
            b, e = make_tracks(args.boxes, frames, rng)
            many.append(box_flows(f"s{n}", b[0], {t: b[t] for t in frames}, e))
        save_flow_records(Path(tmp) / "many.npz", many)
        bundle = (Path(tmp) / "many.npz").stat().st_size / len(many)
    raw = sum(a.nbytes for a in record.arrays().values())
    results.add({"disk_bytes_one_record": single, "disk_bytes_per_keyframe_bundled": bundle, "raw_bytes": raw},
                f"disk: {single} B for one record in its own .npz; {bundle:.0f} B/keyframe in a 200-keyframe bundle; "
                f"raw arrays {raw} B (official voxel lists ≈ 260 KB/keyframe)")


if __name__ == "__main__":
    main()
