"""`occflownet synth`: write a synthetic driving world in the exact nuScenes (+ lidarseg + Occ3D) layout."""
import sys

from occflownet.synth.generate import DEFAULT_SWEEPS

HELP = "synthetic nuScenes-format world (images, LiDAR sweeps, lidarseg, boxes), labelled by `occflownet labels`"


def add_arguments(parser):
    parser.add_argument("--out", required=True, help="dataset root to write (DIR/<version>/, DIR/samples/, ...)")
    parser.add_argument("--scenes", type=int, default=1, help="number of scenes (default 1; the last is val if >= 2)")
    parser.add_argument("--frames", type=int, default=6, help="keyframes per scene, 2 Hz (default 6)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; same seed, same files (default 0)")
    parser.add_argument("--width", type=int, default=480, help="image width in pixels (default 480, 0.3 x nuScenes)")
    parser.add_argument("--height", type=int, default=270, help="image height in pixels (default 270)")
    parser.add_argument("--sweeps", type=int, default=DEFAULT_SWEEPS,
                        help=f"LiDAR sweeps between consecutive keyframes (default {DEFAULT_SWEEPS}; nuScenes has 9)")
    parser.add_argument("--version", default="v1.0-trainval", help="dataset version folder (default v1.0-trainval)")
    parser.add_argument("--preview", action="store_true", help="also write DIR/preview/<sample token>.png")
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset already in DIR")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    g = parser.add_argument_group("scene size")
    g.add_argument("--margin", type=float, default=100.0,
                   help="world extent in metres beyond the ego's path and to each side (default 100)")
    g.add_argument("--lanes", type=int, nargs=2, default=(1, 2), metavar=("MIN", "MAX"),
                   help="lanes per direction, drawn per scene (default 1 2)")
    g.add_argument("--ego-speed", type=float, nargs=2, default=(4.0, 8.0), metavar=("MIN", "MAX"),
                   help="ego speed range in m/s (default 4 8)")
    g.add_argument("--traffic", type=float, default=1.0, help="vehicle density scale (default 1)")
    g.add_argument("--pedestrians", type=float, default=1.0, help="pedestrian density scale (default 1)")
    g.add_argument("--cross-street", type=float, default=0.7,
                   help="probability of a cross street per scene (default 0.7)")


def run(args) -> int:
    from occflownet.synth.generate import generate
    from occflownet.synth.layout import WorldConfig

    try:
        config = WorldConfig(margin=args.margin, ego_speed=tuple(args.ego_speed), lanes=tuple(args.lanes),
                             traffic=args.traffic, pedestrians=args.pedestrians,
                             cross_street_probability=args.cross_street)
        result = generate(args.out, scenes=args.scenes, frames=args.frames, seed=args.seed, width=args.width,
                          height=args.height, version=args.version, preview=args.preview, config=config,
                          progress=not args.no_progress, overwrite=args.overwrite, sweeps=args.sweeps)
    except (ValueError, FileExistsError) as e:
        print(f"occflownet synth: {e}", file=sys.stderr)
        return 2
    print(f"wrote {result.num_samples} keyframes in {len(result.scene_names)} scene(s) to {result.root} "
          f"(version {result.version}) in {result.seconds:.1f} s")
    return 0
