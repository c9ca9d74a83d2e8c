"""`occflownet prepare`: build the sample index of a nuScenes-format root, count classes, precompute flow.

Writes DATAROOT/occflownet/<version>/index.npz + index.json once; later commands load it (fast).
Re-running is idempotent: the index is rebuilt from the tables (same content), and the class counts are reused
when neither the index nor the counted split nor the ray settings changed (``--recount`` forces a recount).
"""
import sys

HELP = "build the sample index (temporal neighbours, splits), class counts and weights, flow"


def add_arguments(parser):
    parser.add_argument("--dataroot", required=True, help="nuScenes-format root (holds <version>/*.json)")
    parser.add_argument("--version", default=None,
                        help="table directory, e.g. v1.0-mini (default: the only one under DATAROOT)")
    parser.add_argument("--split", default=None,
                        help="split whose LiDAR points are counted for the class weights "
                             "(default: 'train' when the root defines it, else 'all')")
    parser.add_argument("--verify-files", action="store_true",
                        help="check that every image, LiDAR, lidarseg and Occ3D file referenced exists")
    parser.add_argument("--recount", action="store_true", help="recount classes even if the counts are current")
    parser.add_argument("--flow-horizon", type=int, default=3,
                        help="frames t in [-O, O] for which box flows are precomputed (training's --horizon <= O)")
    parser.add_argument("--skip-class-counts", action="store_true",
                        help="write the index only (e.g. a root without nuScenes-lidarseg)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    import hashlib
    import json

    from occflownet.data.builder import build_index
    from occflownet.data.class_weights import compute_class_stats
    from occflownet.data.index import index_dir, save_index
    from occflownet.data.rays import RayBuilder, RayConfig
    from occflownet.data.tables import DatasetError

    print(f"reading the tables under {args.dataroot} ...", file=sys.stderr)
    try:
        index = build_index(args.dataroot, args.version, verify_files=args.verify_files)
    except DatasetError as e:
        print(f"occflownet prepare: {e}", file=sys.stderr)
        return 1
    _print_summary(index)

    if not args.skip_class_counts:
        split = args.split or ("train" if "train" in index.splits else "all")
        if split not in index.splits:
            print(f"occflownet prepare: unknown split {split!r}; available: {', '.join(index.available_splits())}",
                  file=sys.stderr)
            return 2
        config = RayConfig()
        digest = hashlib.sha256()
        for name in sorted(index.arrays):
            digest.update(name.encode() + index.arrays[name].tobytes())
        digest.update(json.dumps([split, index.splits[split], config.min_depth, config.ignored_raw_labels]).encode())
        fingerprint = digest.hexdigest()
        previous = _previous_meta(index_dir(args.dataroot, index.version))
        if not args.recount and previous.get("class_stats_fingerprint") == fingerprint and "class_stats" in previous:
            index.meta["class_stats"] = previous["class_stats"]
            print(f"class counts: up to date (split {split}), reused", file=sys.stderr)
        else:
            try:
                stats = compute_class_stats(RayBuilder(index, args.dataroot, config, cache_size=0), split,
                                            progress=not args.quiet)
            except DatasetError as e:
                print(f"occflownet prepare: {e}", file=sys.stderr)
                return 1
            index.meta["class_stats"] = stats.to_dict()
        index.meta["class_stats_fingerprint"] = fingerprint
        _print_class_stats(index.class_stats)

    out = save_index(index, args.dataroot)
    print(f"index written to {out}")

    # Occupancy flow of dynamic boxes, written beside the index (versioned by FLOW_FORMAT_VERSION).
    from occflownet.data.flow import precompute_flow

    path = precompute_flow(index, args.dataroot, horizon=args.flow_horizon, progress=not args.quiet)
    print(f"flow records written to {path}")
    return 0


def _previous_meta(folder) -> dict:
    import json

    try:
        return json.loads((folder / "index.json").read_text())
    except (OSError, ValueError):
        return {}


def _print_summary(index) -> None:
    a = index.arrays
    with_seg = int((a["lidarseg_path"] != b"").sum())
    with_occ = int((a["occupancy_path"] != b"").sum())
    print(f"{index.version}: {len(index)} keyframes in {len(index.scene_names)} scenes, "
          f"{len(a['box_label'])} boxes; lidarseg for {with_seg}, Occ3D occupancy for {with_occ}")
    for name in index.available_splits():
        print(f"  split {name}: {len(index.splits[name])} scenes, {len(index.split_positions(name))} keyframes")


def _print_class_stats(stats) -> None:
    from occflownet.occ3d import CLASS_NAMES

    print(f"class counts over split '{stats.split}' ({stats.num_samples} keyframes): class, N_c, weight")
    for c, (n, w) in enumerate(zip(stats.counts, stats.weights)):
        print(f"  {c:2d} {CLASS_NAMES[c]:<22s} {int(n):>12d} {w:7.3f}")
