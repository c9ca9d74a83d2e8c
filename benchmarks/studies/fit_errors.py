"""Where a trained model's errors lie on the keyframes it was trained on (the fitting protocol's runs,
``benchmarks/studies/fitting.py``): what the labelled voxels of each class are predicted as, where the false
positives lie relative to the labelled surfaces, and where the light of the training rays stops, by the class of
their point.

    python -m benchmarks.studies.fit_errors --run F/recipe/seed0/recommended --world F/world [--keyframes 2,5]

Prints, over every keyframe of the world, inside ``mask_camera`` (EMA weights, the run's τ):

- per class with ≥ 50 labelled voxels: IoU, the share predicted free, of the right class, and the top confusions;
- the false positives (predicted occupied, labelled free): by distance to the nearest labelled-occupied voxel, and
  by side: stepping radially away from the ego (origin 1.5 m above the ego frame's origin) a labelled surface
  within 15 voxels ("in front of a surface"), stepping towards it ("behind"), or neither; for those in front, the
  gap as a share of the surface's range, and which classes they stand in front of;
- geometry IoU by τ;
- for the t = 0 training rays of ``--keyframes`` by class of their point: the rendered opacity, the share of the
  light stopped before depth − 0.6 m, within ±0.6 m and after depth + 0.6 m, the median rendered-depth error
  (depth Σ w_i t_i minus the LiDAR distance) and the median σ of the voxel holding the point (docs/results.md:
  a 2D model whose light passes through the cars and stops behind them has not carved the road, it has carved
  the cars).
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy import ndimage

from occflownet.data.index import load_index
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.rays import RayBuilder, RayConfig
from occflownet.eval.evaluate import select_samples
from occflownet.model.checkpoint import load_checkpoint
from occflownet.occ3d import CLASS_NAMES, FREE, GRID
from occflownet.render.volume_render import RenderConfig, render_rays

GROUND = (11, 12, 13, 14)           # driveable_surface, other_flat, sidewalk, terrain
EGO_EYE = np.array([0.0, 0.0, 1.5])  # where "radially" starts: about the cameras' height above the ego frame


def predict(model, dataroot, record):
    """(σ [X, Y, Z], logits [X, Y, Z, 17]) of one keyframe, float32 tensors."""
    with torch.inference_mode():
        out = model(torch.from_numpy(load_sample_images(dataroot, record))[None],
                    torch.from_numpy(np.asarray(record.intrinsics, np.float32))[None],
                    torch.from_numpy(np.asarray(record.cam2current_ego(), np.float32))[None])
    return out["density"][0].float(), out["logits"][0].float()


def radial_side(false_pos: np.ndarray, occupied: np.ndarray, steps: int = 15):
    """For the voxels ``false_pos`` (bool [X, Y, Z]): side int [K] (0 in front of a labelled-occupied voxel of
    ``occupied`` along the ray from EGO_EYE, 1 behind one, 2 neither), the gap / range of those in front, and the
    class index position (flat) of the surface they stand in front of (-1 elsewhere)."""
    centres = np.asarray(GRID.lower) + (np.argwhere(false_pos) + 0.5) * GRID.voxel_size
    u = centres - EGO_EYE
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    side = np.full(len(centres), 2)
    gap = np.full(len(centres), np.nan)
    surface = np.full(len(centres), -1, dtype=np.int64)
    shape = np.asarray(GRID.shape)
    for k in range(1, steps + 1):
        for sign, code in ((1, 0), (-1, 1)):
            q = centres + sign * k * GRID.voxel_size * u
            ijk = GRID.index_of(q)
            inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
            hit = np.zeros(len(q), dtype=bool)
            hit[inside] = occupied[tuple(ijk[inside].T)]
            new = (side == 2) & hit
            if code == 0:
                gap[new] = k * GRID.voxel_size / np.linalg.norm(q[new] - EGO_EYE, axis=1)
                surface[new] = np.ravel_multi_index(tuple(ijk[new].T), GRID.shape)
            side[new] = code
    return side, gap, surface


def light_profile(model, root, index, position: int, classes=(15, 16, 11, 4, 10, 3)) -> list[str]:
    """Lines: where the light of the t = 0 training rays of one keyframe stops, by class of their point."""
    density, logits = predict(model, root, index[position])
    rays = RayBuilder(index, root, RayConfig(horizon=0)).rays(position)
    lines = []
    for c in classes:
        of_class = np.flatnonzero(rays.labels == c)
        if len(of_class) < 30:
            continue
        pick = of_class[np.random.default_rng(0).choice(len(of_class), min(2000, len(of_class)), replace=False)]
        out = render_rays(density, logits, torch.from_numpy(rays.origins[pick]), torch.from_numpy(rays.directions[pick]),
                          RenderConfig(), torch.Generator().manual_seed(0))
        w = out.weights.numpy()
        t = (0.5 * (out.t_starts + out.t_ends)).numpy()
        d = rays.depths[pick][:, None]
        ends = rays.origins[pick] + rays.depths[pick][:, None] * rays.directions[pick]
        inside = GRID.contains(ends)
        sigma_end = density.numpy()[tuple(GRID.index_of(ends[inside]).T)]
        lines.append(f"  keyframe {position} {CLASS_NAMES[c]:18s} rays {len(pick):5d}  opacity {w.sum(1).mean():.2f}  "
                     f"stopped before d-0.6 m {(w * (t < d - 0.6)).sum(1).mean():.2f}, within ±0.6 m "
                     f"{(w * (np.abs(t - d) <= 0.6)).sum(1).mean():.2f}, after {(w * (t > d + 0.6)).sum(1).mean():.2f}"
                     f"  depth error median {np.median(out.depth.numpy() - rays.depths[pick]):+.2f} m"
                     f"  σ at the point's voxel median {np.median(sigma_end):.2f}  (depth median "
                     f"{np.median(rays.depths[pick]):.1f} m)")
    return lines


def collect(model, samples) -> dict:
    """Over every keyframe of ``samples``, inside ``mask_camera``: the confusion [18, 18] (labels × predictions,
    17 = free), the false positives' distances, sides, gaps and fronted classes, σ at labelled-occupied and
    labelled-free voxels."""
    tau = model.cfg.threshold
    found = {"confusion": np.zeros((FREE + 1, FREE + 1), dtype=np.int64), "distances": [], "sides": [], "gaps": [],
             "fronted": [], "sigma_occupied": [], "sigma_free": []}
    for position in samples.positions:
        record = samples.index[int(position)]
        density, logits = predict(model, samples.dataroot, record)
        sigma, classes = density.numpy(), logits.argmax(-1).numpy()
        occ = load_occupancy(samples.dataroot, record.occupancy_path)
        labels, mask = occ.semantics.astype(np.int64), occ.mask_camera.astype(bool)
        predicted = np.where(sigma >= tau, classes, FREE)
        found["confusion"] += np.bincount(labels[mask] * (FREE + 1) + predicted[mask],
                                          minlength=(FREE + 1) ** 2).reshape(FREE + 1, FREE + 1)
        occupied = labels != FREE
        false_pos = mask & ~occupied & (predicted != FREE)
        found["distances"].append(ndimage.distance_transform_edt(~occupied)[false_pos])
        side, gap, surface = radial_side(false_pos, occupied)
        found["sides"].append(side)
        found["gaps"].append(gap[side == 0])
        found["fronted"].append(labels.reshape(-1)[surface[side == 0]])
        found["sigma_occupied"].append(sigma[mask & occupied])
        found["sigma_free"].append(sigma[mask & ~occupied])
    return found


def report(found: dict) -> list[str]:
    """The printed lines of :func:`collect`'s figures (see the module docstring)."""
    confusion = found["confusion"]
    lines = []
    labelled = confusion[:FREE].sum(1)
    for c in np.flatnonzero(labelled >= 50):
        row = confusion[c]
        iou = row[c] / (row.sum() + confusion[:, c].sum() - row[c])
        top = ", ".join(f"{'free' if j == FREE else CLASS_NAMES[j]} {row[j] / labelled[c]:.2f}"
                        for j in np.argsort(-row)[:4] if row[j])
        lines.append(f"  {CLASS_NAMES[c]:20s} labelled {labelled[c]:7d}  IoU {iou:.2f}  predicted free "
                     f"{row[FREE] / labelled[c]:.2f}  right {row[c] / labelled[c]:.2f}  ({top})")
    d, side, gap, front_of = (np.concatenate(found[k]) for k in ("distances", "sides", "gaps", "fronted"))
    lines.append(f"false positives {len(d)}: at distance 1 / 2 / 3 / 4-6 / 7+ voxels from a labelled-occupied voxel: "
                 + " / ".join(str(int(n)) for n in np.histogram(d, [0, 1.01, 2.01, 3.01, 6.01, np.inf])[0]))
    lines.append(f"  in front of a labelled surface {int((side == 0).sum())}, behind one {int((side == 1).sum())}, "
                 f"neither within 15 voxels {int((side == 2).sum())}")
    if len(gap):
        ground = np.isin(front_of, GROUND).mean()
        lines.append(f"  in front: gap / the surface's range, quartiles "
                     f"{np.percentile(gap, [25, 50, 75]).round(3).tolist()}; in front of ground classes {ground:.2f}, "
                     f"of others {1 - ground:.2f}")
        lines += [f"    in front of {CLASS_NAMES[c]}: {n}" for c, n in zip(*np.unique(front_of, return_counts=True))
                  if n >= 500]
    so, sf = np.concatenate(found["sigma_occupied"]), np.concatenate(found["sigma_free"])
    lines.append(f"σ at labelled-occupied voxels, deciles 1/5/9: {np.percentile(so, [10, 50, 90]).round(3).tolist()}; "
                 f"at labelled-free ones, 50/90/99 %: {np.percentile(sf, [50, 90, 99]).round(3).tolist()}")
    lines.append("geometry IoU by τ: " + ", ".join(
        f"{t:g}: {(so >= t).sum() / ((so >= t).sum() + (sf >= t).sum() + (so < t).sum()):.3f}"
        for t in (0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.9)))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a training run folder (checkpoints/last.pt)")
    ap.add_argument("--world", required=True, help="the prepared root it was trained on")
    ap.add_argument("--keyframes", default="2,5", help="positions whose t = 0 rays are profiled")
    args = ap.parse_args()
    model, _, _ = load_checkpoint(f"{args.run}/checkpoints/last.pt")
    model.eval()
    samples = select_samples(args.world, split="all")
    print(f"{args.run}: τ = {model.cfg.threshold}, {len(samples.positions)} keyframes of {args.world}, inside "
          f"mask_camera")
    print("\n".join(report(collect(model, samples))))
    print("where the light of the t = 0 training rays stops:")
    index = load_index(args.world)
    for position in (int(k) for k in args.keyframes.split(",")):
        print("\n".join(light_profile(model, args.world, index, position)))


if __name__ == "__main__":
    main()
