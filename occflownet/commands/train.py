"""`occflownet train`: train a model from a prepared nuScenes-format root (single process or under torchrun).

A run is a named recipe (``--recipe``, default ``recommended``; ``occflownet recipes`` lists them) or a recorded run
(``--config RUN/train_config.json``), with the options given on the command line over its values. The options are
the fields of :class:`occflownet.train.recipe.TrainConfig` (``occflownet/options.py``: names, help, choices, smallest
values and ``--help`` groups come from the dataclass; the defaults shown are the default recipe's), plus
``--config``, ``--resume`` and ``--quiet``."""
import argparse
import sys

from occflownet.options import add_options, config_kwargs
from occflownet.train.recipe import GROUPS, OUTPUT, RUN, TrainConfig
from occflownet.train.recipes import DEFAULT_RECIPE, RECIPES

HELP = "train a model from a named recipe (2D rendering, temporal frames, dynamic handling, occupancy flow, 3D labels)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of TrainConfig, in their groups; an option left out is the recipe's (or the recorded run's)."""
    shown = {"recipe": DEFAULT_RECIPE, "dataroot": None, "out": None, "version": None,
             **RECIPES[DEFAULT_RECIPE].settings}
    p.epilog = (f"An option left out takes the recipe's value (the defaults shown are those of {DEFAULT_RECIPE!r}; "
                "`occflownet recipes` lists the recipes), or with --config the recorded run's.")
    add_options(p, TrainConfig, given_only=True, defaults=shown, groups=GROUPS)
    groups = {g.title: g for g in p._action_groups}
    groups[RUN].add_argument("--config", default=None, metavar="RUN/train_config.json",
                             help="rerun a recorded run: its configuration, with the options given over it "
                                  "(not with --recipe)")
    groups[RUN].add_argument("--resume", action="store_true", help="continue from <out>/checkpoints/last.pt")
    groups[OUTPUT].add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args) -> TrainConfig:
    """The TrainConfig of the parsed options: the recipe's values (or the recorded run's, with ``--config``) with
    the options given over them; ``--version`` unset: the root's only table version. ValueError / FileNotFoundError
    for a bad combination, recipe or file."""
    from occflownet.data.index import load_index

    given = config_kwargs(args, TrainConfig)
    if args.config:
        if "recipe" in given:
            raise ValueError("--config reruns a recorded run; give --recipe or --config, not both")
        return TrainConfig(**{**TrainConfig.from_json(args.config).to_dict(), **given})
    if "dataroot" not in given or "out" not in given:
        raise ValueError("--dataroot and --out are required (or --config RUN/train_config.json)")
    if "version" not in given:
        given["version"] = load_index(given["dataroot"], None, check_tables=False).version
    return TrainConfig.from_recipe(given.pop("recipe", DEFAULT_RECIPE), **given)


def describe(cfg: TrainConfig) -> str:
    """What a run is, printed before it starts: its recipe, where it differs from it, and every resolved value."""
    changes = cfg.recipe_changes()
    lines = [f"recipe {cfg.recipe!r}: {RECIPES[cfg.recipe].description}"]
    if changes:
        changed = ", ".join(f"{k}={new!r} (recipe: {old!r})" for k, (old, new) in changes.items())
        lines.append(f"  changed: {changed} -- not a measured recipe")
    values = " ".join(f"{k}={v}" for k, v in cfg.to_dict().items())
    lines.append(f"  configuration: {values}")
    return "\n".join(lines)


def run(args) -> int:
    from occflownet.data.tables import DatasetError
    from occflownet.train.loop import TrainingError, train

    try:
        cfg = config_from_args(args)
        print(describe(cfg), file=sys.stderr)
        path = train(cfg, resume=args.resume, progress=not args.quiet)
    except (TrainingError, DatasetError, FileNotFoundError, KeyError, ValueError) as e:
        print(f"occflownet train: error: {e}", file=sys.stderr)
        return 1
    print(f"checkpoint: {path}", file=sys.stderr)
    return 0
