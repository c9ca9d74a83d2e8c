"""`occflownet synth`: write a synthetic driving world in the exact nuScenes (+ lidarseg + Occ3D) layout.

The options are the fields of :class:`occflownet.synth.generate.SynthConfig` and, in their own section, of
:class:`occflownet.synth.layout.WorldConfig` (``occflownet/options.py``), plus ``--out`` and ``--no-progress``."""
import sys

from occflownet.options import add_options, config_kwargs
from occflownet.synth.generate import SynthConfig
from occflownet.synth.layout import SCENE_SIZE, WorldConfig

HELP = "synthetic nuScenes-format world (images, LiDAR sweeps, lidarseg, boxes), labelled by `occflownet labels`"
WORLD_SKIP = ("raster_res",)    # not a command-line option


def add_arguments(parser):
    parser.add_argument("--out", required=True, help="dataset root to write (DIR/<version>/, DIR/samples/, ...)")
    add_options(parser, SynthConfig)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    add_options(parser, WorldConfig, skip=WORLD_SKIP,
                groups=[(SCENE_SIZE, "how large and busy each scene is (drawn per scene within these ranges)")])


def run(args) -> int:
    from occflownet.synth.generate import generate

    try:
        world = WorldConfig(**config_kwargs(args, WorldConfig, skip=WORLD_SKIP))
        result = generate(args.out, SynthConfig(**config_kwargs(args, SynthConfig)), config=world,
                          progress=not args.no_progress)
    except (ValueError, FileExistsError) as e:
        print(f"occflownet synth: {e}", file=sys.stderr)
        return 2
    print(f"wrote {result.num_samples} keyframes in {len(result.scene_names)} scene(s) to {result.root} "
          f"(version {result.version}) in {result.seconds:.1f} s")
    return 0
