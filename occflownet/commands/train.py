"""`occflownet train`: train a model from a prepared nuScenes-format root (single process or under torchrun).

The options are the fields of :class:`occflownet.train.recipe.TrainConfig` (``occflownet/options.py``: names,
defaults, help and choices come from the dataclass), plus ``--resume`` and ``--quiet``."""
import argparse

from occflownet.options import add_options, config_kwargs
from occflownet.train.recipe import TrainConfig

HELP = "train a model (2D rendering, temporal frames, dynamic handling, occupancy flow, optional 3D labels)"
REQUIRED = ("dataroot", "out")
CLI_DEFAULTS = {"version": None}  # None: the root's only table version


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of TrainConfig; those of the preset's recipe (PRESET_RECIPES) default to None = the preset's."""
    add_options(p, TrainConfig, required=REQUIRED, defaults=CLI_DEFAULTS)
    p.add_argument("--resume", action="store_true", help="continue from <out>/checkpoints/last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args) -> TrainConfig:
    """The TrainConfig of the parsed options (``--version`` unset: the root's only table version)."""
    from occflownet.data.index import load_index

    kwargs = config_kwargs(args, TrainConfig)
    if kwargs["version"] is None:
        kwargs["version"] = load_index(args.dataroot, None, check_tables=False).version
    return TrainConfig(**kwargs)


def run(args) -> int:
    import sys

    from occflownet.data.tables import DatasetError
    from occflownet.train.loop import TrainingError, train

    try:
        cfg = config_from_args(args)
        path = train(cfg, resume=args.resume, progress=not args.quiet)
    except (TrainingError, DatasetError, FileNotFoundError, KeyError, ValueError) as e:
        print(f"occflownet train: error: {e}", file=sys.stderr)
        return 1
    print(f"checkpoint: {path}", file=sys.stderr)
    return 0
