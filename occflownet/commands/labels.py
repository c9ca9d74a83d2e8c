"""`occflownet labels`: Occ3D ground truth (semantics, mask_lidar, mask_camera) from a root's LiDAR, boxes and
lidarseg (:func:`occflownet.labels.label_root`; docs/data.md).

The options are the fields of :class:`occflownet.labels.LabelRun` (what is read and written) and of
:class:`occflownet.labels.LabelConfig` (how the labels are made; its rules' thresholds in their own section)
(``occflownet/options.py``), plus ``--dataroot`` and ``--quiet``."""
import sys

from occflownet.labels.config import RULES, LabelConfig
from occflownet.labels.pipeline import LabelRun
from occflownet.options import add_options, config_kwargs

HELP = "Occ3D labels (semantics, mask_lidar, mask_camera) for every keyframe, from LiDAR sweeps, boxes and lidarseg"
CONFIG_SKIP = ("ego_box", "grid")       # not command-line options


def add_arguments(parser):
    parser.add_argument("--dataroot", required=True, help="nuScenes-format root (holds <version>/*.json)")
    add_options(parser, LabelRun)
    add_options(parser, LabelConfig, skip=CONFIG_SKIP,
                groups=[(RULES, "the thresholds of the rules (docs/data.md); the settings are recorded in "
                                "gts/labels.json, and a rerun with others needs --overwrite")])
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from occflownet.data.tables import DatasetError
    from occflownet.labels import label_root

    try:
        run_config = LabelRun(**config_kwargs(args, LabelRun))
        config = LabelConfig(**config_kwargs(args, LabelConfig, skip=CONFIG_SKIP))
        report = label_root(args.dataroot, config, run_config, progress=not args.quiet)
    except ValueError as e:         # DatasetError and LabelError are ValueErrors too
        kind = "" if isinstance(e, DatasetError) else "bad option: "
        print(f"occflownet labels: {kind}{e}", file=sys.stderr)
        return 1 if isinstance(e, DatasetError) else 2
    for w in report.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"labelled {report.written} keyframes ({report.skipped} already done) of {len(report.scenes)} scene(s) "
          f"in {report.seconds:.1f} s; written under {report.out}")
    return 0
