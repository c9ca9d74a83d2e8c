"""`occflownet labels`: Occ3D ground truth (semantics, mask_lidar, mask_camera) from a root's LiDAR, boxes and
lidarseg (:func:`occflownet.labels.label_root`; docs/labels.md)."""
import sys

HELP = "Occ3D labels (semantics, mask_lidar, mask_camera) for every keyframe, from LiDAR sweeps, boxes and lidarseg"


def add_arguments(parser):
    parser.add_argument("--dataroot", required=True, help="nuScenes-format root (holds <version>/*.json)")
    parser.add_argument("--version", default=None, help="table directory (default: the only one under DATAROOT)")
    parser.add_argument("--out", default=None, help="write OUT/gts/... instead of DATAROOT/gts/...")
    parser.add_argument("--window", type=int, default=None,
                        help="accumulate the sweeps of K keyframes on each side (default: the whole scene, as Occ3D)")
    parser.add_argument("--geometry-only", action="store_true",
                        help="occupancy and masks without classes (a root without nuScenes-lidarseg): class 0 for "
                             "every occupied voxel")
    parser.add_argument("--workers", type=int, default=1, help="scenes labelled in parallel processes (default 1)")
    parser.add_argument("--shard", default="0/1", metavar="I/N",
                        help="label the scenes whose position in name order is I mod N (default 0/1: all)")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo existing labels (also those made with other settings or by another tool)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from occflownet.data.tables import DatasetError
    from occflownet.labels import LabelConfig, label_root

    try:
        shard = tuple(int(v) for v in args.shard.split("/"))
        if len(shard) != 2:
            raise ValueError
    except ValueError:
        print(f"occflownet labels: --shard must be I/N, got {args.shard!r}", file=sys.stderr)
        return 2
    try:
        config = LabelConfig(window=args.window, geometry_only=args.geometry_only)
        report = label_root(args.dataroot, args.version, config, out=args.out, workers=args.workers, shard=shard,
                            overwrite=args.overwrite, progress=not args.quiet)
    except ValueError as e:         # DatasetError and LabelError are ValueErrors too
        kind = "" if isinstance(e, DatasetError) else "bad option: "
        print(f"occflownet labels: {kind}{e}", file=sys.stderr)
        return 1 if isinstance(e, DatasetError) else 2
    for w in report.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"labelled {report.written} keyframes ({report.skipped} already done) of {len(report.scenes)} scene(s) "
          f"in {report.seconds:.1f} s; written under {report.out}")
    return 0
