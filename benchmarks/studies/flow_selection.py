"""How much of each moving object occupancy flow actually moves, for a trained checkpoint.

Occupancy flow (``occflownet/render/occupancy_flow.py``) moves, into the copy of frame t, the voxels of a dynamic box
whose *predicted* class (argmax of the semantic logits) is the box's class. The object's voxels it does not select
stay where they were at t = 0, and with ``--flow`` the dynamic filter is off, so the rays of frame t that end on the
object render through them: the smear of the temporal rows without the filter (row 4). This prints, over every
keyframe of a split and every move of its flow record (t ∈ [-O, O] \\ {0}):

- recall: of the labelled voxels of the box's class inside the enlarged box at t = 0 (the object), the share that
  flow selects (``selected_sources``, the warp's own rule: predicted class = box class, a voxel in several boxes
  moving with one) — the rest stays behind;
- dense recall: the same, counting only the labelled voxels the model also predicts occupied (σ ≥ τ);
- precision: of the selected voxels, the share labelled with the box's class (the rest: free space or other
  classes inside the enlarged box, carried along with the object);
- selected mass: Σσ of the selected voxels over Σσ of the labelled object voxels (how much density moves);
- ray coverage (no checkpoint needed): of the rays of frames t ≠ 0 labelled with a dynamic-filter class (the rays
  that ``--flow`` keeps and row 5 drops), the share that end within ``--margin`` metres of a box that flow moves
  into frame t; the rest end on objects flow cannot move (no box, or a box not matched at t = 0). LiDAR points on
  a vehicle lie on its box's faces, so at margin 0 about a third fall just outside it.

    python -m benchmarks.studies.flow_selection --checkpoint RUN/checkpoints/last.pt --dataroot WORLD [--split all]
        [--horizon 3] [--margin 0.2]
    python -m benchmarks.studies.flow_selection --dataroot WORLD      # ray coverage only
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from occflownet.contract import Calibration
from occflownet.data.flow import flow_moves, keyframe_flow
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.rays import RayBuilder, RayConfig
from occflownet.eval.evaluate import select_samples
from occflownet.model.checkpoint import model_from_source
from occflownet.occ3d import CLASS_NAMES, DYNAMIC_FILTER_CLASSES, NUM_CLASSES
from occflownet.render.occupancy_flow import PackedMoves, selected_sources
from occflownet.runtime import frame_inputs


def ray_coverage(samples, rays: RayBuilder, position: int, horizon: int, margin: float) -> dict:
    """{"dynamic_rays": n, "covered": n, "uncovered_by_class": {name: n}} for the rays of keyframe ``position``'s
    frames t ≠ 0 labelled with a dynamic-filter class (current ego frame, as training builds them)."""
    sample = samples.index[position]
    flow = keyframe_flow(samples.index, position, horizon)
    batch = rays.rays(position)
    ends = batch.endpoints()
    out = {"dynamic_rays": 0, "covered": 0, "uncovered_by_class": {}}
    for t, j in samples.index.neighbours(position, horizon):
        if t == 0:
            continue
        chosen = (batch.time_offsets == t) & np.isin(batch.labels, DYNAMIC_FILTER_CLASSES)
        moved = sample.boxes.instance_tokens[flow.box_index[flow.move_box[flow.offset == t]]]
        boxes_t = samples.index[j].boxes.in_frame(sample.ego2global)     # frame t's boxes, current ego frame
        inside = boxes_t.contains(ends[chosen], margin=margin)[np.isin(boxes_t.instance_tokens, moved)]
        covered = inside.any(0) if len(inside) else np.zeros(int(chosen.sum()), bool)
        out["dynamic_rays"] += int(chosen.sum())
        out["covered"] += int(covered.sum())
        for c, n in zip(*np.unique(batch.labels[chosen][~covered], return_counts=True)):
            name = CLASS_NAMES[int(c)]
            out["uncovered_by_class"][name] = out["uncovered_by_class"].get(name, 0) + int(n)
    return out


def keyframe_selection(model, samples, position: int, horizon: int) -> dict:
    """Counts for one keyframe, summed over its moves (see the module docstring)."""
    record = samples.index[position]
    inputs = frame_inputs(load_sample_images(samples.dataroot, record),
                          Calibration.from_arrays(record.intrinsics, record.cam2current_ego()))
    with torch.inference_mode():
        out = model(torch.from_numpy(inputs.images), torch.from_numpy(inputs.intrinsics),
                    torch.from_numpy(inputs.cam2ego))
    sigma = out["density"][0].numpy()                                    # [X, Y, Z]
    dense = sigma >= model.cfg.threshold
    labels = load_occupancy(samples.dataroot, record.occupancy_path).semantics
    flow = keyframe_flow(samples.index, position, horizon)
    offsets = sorted({int(t) for t in flow.offset})
    moves = PackedMoves.from_arrays(**flow_moves(flow, offsets))
    # the warp's own selection (one volume per offset, all read from this keyframe's prediction)
    rows = selected_sources(out["logits"].reshape(1, -1, NUM_CLASSES), torch.zeros(len(offsets), dtype=torch.long),
                            moves)
    selected = np.zeros(len(moves.voxels), dtype=bool)
    selected[rows.numpy()] = True
    voxels, box = moves.voxels.numpy(), moves.box.numpy()
    counts = dict(object=0, object_dense=0, selected=0, selected_object=0, selected_object_dense=0,
                  object_mass=0.0, selected_mass=0.0, moves=moves.num_moves)
    for k, cls in enumerate(moves.classes.tolist()):
        mine = box == k
        x, y, z = voxels[mine].T
        is_object, chosen = labels[x, y, z] == cls, selected[mine]
        occupied, mass = dense[x, y, z], sigma[x, y, z]
        counts["object"] += int(is_object.sum())
        counts["object_dense"] += int((is_object & occupied).sum())
        counts["selected"] += int(chosen.sum())
        counts["selected_object"] += int((chosen & is_object).sum())
        counts["selected_object_dense"] += int((chosen & is_object & occupied).sum())
        counts["object_mass"] += float(mass[is_object].sum())
        counts["selected_mass"] += float(mass[chosen].sum())
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", help="a trained checkpoint (without one: the ray coverage only)")
    ap.add_argument("--dataroot", required=True)
    ap.add_argument("--split", default="all")
    ap.add_argument("--horizon", type=int, default=3)
    ap.add_argument("--margin", type=float, default=0.2, help="metres around a box that count as on it")
    args = ap.parse_args()
    samples = select_samples(args.dataroot, split=args.split)
    builder = RayBuilder(samples.index, samples.dataroot, RayConfig(horizon=args.horizon, dynamic_filter=False))
    coverage = {"dynamic_rays": 0, "covered": 0, "uncovered_by_class": {}}
    for position in samples.positions:
        part = ray_coverage(samples, builder, int(position), args.horizon, args.margin)
        coverage["dynamic_rays"] += part["dynamic_rays"]
        coverage["covered"] += part["covered"]
        for name, n in part["uncovered_by_class"].items():
            coverage["uncovered_by_class"][name] = coverage["uncovered_by_class"].get(name, 0) + n
    coverage["share_covered"] = round(coverage["covered"] / max(coverage["dynamic_rays"], 1), 4)
    print(json.dumps({"dataroot": args.dataroot, "margin": args.margin, "ray_coverage": coverage}))
    if args.checkpoint is None:
        return
    model = model_from_source(args.checkpoint)
    total: dict = {}
    for position in samples.positions:
        for key, value in keyframe_selection(model, samples, int(position), args.horizon).items():
            total[key] = total.get(key, 0) + value
    share = lambda a, b: None if not total[b] else round(total[a] / total[b], 4)  # noqa: E731
    print(json.dumps({"checkpoint": args.checkpoint, "keyframes": len(samples), "moves": total["moves"],
                      "recall": share("selected_object", "object"),
                      "dense_recall": share("selected_object_dense", "object_dense"),
                      "precision": share("selected_object", "selected"),
                      "selected_mass_over_object_mass": share("selected_mass", "object_mass"),
                      "counts": total}))


if __name__ == "__main__":
    main()
