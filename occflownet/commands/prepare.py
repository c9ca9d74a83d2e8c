"""`occflownet prepare`: build the sample index of a nuScenes-format root, count classes, precompute flow.

The work is :func:`occflownet.data.prepare.prepare`; this module parses the arguments and prints. Re-running is
idempotent; ``--recount`` forces a recount of the classes.
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
    from occflownet.data.prepare import UnknownSplit, prepare
    from occflownet.data.tables import DatasetError

    print(f"reading the tables under {args.dataroot} ...", file=sys.stderr)
    try:
        result = prepare(args.dataroot, args.version, args.split, verify_files=args.verify_files,
                         recount=args.recount, flow_horizon=args.flow_horizon,
                         class_counts=not args.skip_class_counts, progress=not args.quiet, on_index=_print_summary)
    except UnknownSplit as e:
        print(f"occflownet prepare: {e}", file=sys.stderr)
        return 2
    except DatasetError as e:
        print(f"occflownet prepare: {e}", file=sys.stderr)
        return 1
    if result.counts_split is not None:
        if result.counts_reused:
            print(f"class counts: up to date (split {result.counts_split}), reused", file=sys.stderr)
        _print_class_stats(result.index.class_stats)
    print(f"index written to {result.index_dir}")
    print(f"flow records written to {result.flow_path}")
    return 0


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
