"""`occflownet prepare`: build the sample index of a nuScenes-format root, count classes, precompute flow.

The work is :func:`occflownet.data.prepare.prepare`; the options are the fields of
:class:`occflownet.data.prepare.PrepareConfig` (``occflownet/options.py``), plus ``--dataroot`` and ``--quiet``.
Re-running is idempotent; ``--recount`` forces a recount of the classes.
"""
import sys

from occflownet.data.prepare import PrepareConfig
from occflownet.options import add_options, config_kwargs

HELP = "build the sample index (temporal neighbours, splits), class counts and weights, flow"


def add_arguments(parser):
    parser.add_argument("--dataroot", required=True, help="nuScenes-format root (holds <version>/*.json)")
    add_options(parser, PrepareConfig)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from occflownet.data.prepare import UnknownSplit, prepare
    from occflownet.data.tables import DatasetError

    print(f"reading the tables under {args.dataroot} ...", file=sys.stderr)
    try:
        result = prepare(args.dataroot, PrepareConfig(**config_kwargs(args, PrepareConfig)),
                         progress=not args.quiet, on_index=_print_summary)
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
