"""`occflownet train`: train a model from a prepared nuScenes-format root (single process or under torchrun)."""
import argparse

from occflownet.train.recipe import PRESET_RECIPES

HELP = "train a model (2D rendering, temporal frames, dynamic handling, occupancy flow, optional 3D labels)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of TrainConfig; those of the preset's recipe (PRESET_RECIPES) default to None = the preset's."""
    p.add_argument("--preset", default="tiny", choices=sorted(PRESET_RECIPES))
    p.add_argument("--dataroot", required=True, help="nuScenes-format root (run `occflownet prepare` on it first)")
    p.add_argument("--version", default=None, help="table version folder (default: the only one in the root)")
    p.add_argument("--split", default="train")
    p.add_argument("--out", required=True, help="run folder: checkpoints/, log.jsonl, train_config.json")
    p.add_argument("--supervision", default="2d", choices=["2d", "3d", "2d+3d"])
    p.add_argument("--horizon", type=int, default=3, help="temporal frames t in [-O, O] (O = 0: no temporal rays)")
    p.add_argument("--flow", action=argparse.BooleanOptionalAction, default=False, help="occupancy flow")
    p.add_argument("--flow-mover", default="idw", choices=["idw", "nearest"])
    p.add_argument("--dynamic-filter", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--disocclusion", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--loss-weighting", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--depth-loss", action=argparse.BooleanOptionalAction, default=True,
                   help="rendered-depth MSE and LiDAR depth BCE (off: semantics only)")
    p.add_argument("--density-scale", type=float, default=1.0,
                   help="rendering optical depth per metre = scale * sigma (1.0 = the official, unscaled sigma)")
    p.add_argument("--sigma-is", default="density", choices=["density", "opacity"],
                   help="rendering reads σ as a density per metre (official) or an opacity per voxel")
    p.add_argument("--render-depth-weight", type=float, default=0.05, help="weight of the rendered-depth MSE")
    p.add_argument("--render-semantics", default="mixture", choices=["mixture", "normalized"],
                   help="CE on the rendered logit mixture (official) or on it divided by the ray's weight sum")
    p.add_argument("--free-prior-weight", type=float, default=0.0,
                   help="weight of the mean -log(1 - σ) over all voxels (0: off, official)")
    p.add_argument("--voxel-mask", action=argparse.BooleanOptionalAction, default=False,
                   help="3D voxel losses only inside mask_camera (default off: every voxel, as the official code)")
    p.add_argument("--head-init", default="", choices=["", "prior", "official"],
                   help="σ/semantic head init: prior (σ ≈ 0.1 at the start) or official (Xavier, zero bias); "
                        "default: the preset's")
    p.add_argument("--free-space", action=argparse.BooleanOptionalAction, default=False,
                   help="also render LiDAR beams that returned nothing; their opacity goes to 0 (beyond the paper)")
    p.add_argument("--free-rays-per-step", type=int, default=2048, help="free-space beams per sample per step")
    p.add_argument("--free-space-weight", type=float, default=1.0, help="weight of the free-space term")
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--time-limit", type=float, default=0.0, help="stop with a checkpoint after this many seconds")
    p.add_argument("--batch-size", type=int, default=1, help="samples per process per step")
    p.add_argument("--rays-per-step", type=int, default=None,
                   help="rays per sample per step (default: the preset's; official 32768)")
    p.add_argument("--lr", type=float, default=None, help="default: the preset's")
    p.add_argument("--weight-decay", type=float, default=1e-2)
    p.add_argument("--warmup-steps", type=int, default=None, help="default: the preset's")
    p.add_argument("--ema-decay", type=float, default=None, help="default: the preset's")
    p.add_argument("--checkpoint-every", type=int, default=None, help="default: the preset's")
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--num-workers", type=int, default=2)
    p.add_argument("--device", default="auto")
    p.add_argument("--no-amp", action="store_true", help="disable mixed precision on CUDA")
    p.add_argument("--threshold", type=float, default=None, help="τ (default 0.35 for 2d, 0.30 with 3D labels)")
    p.add_argument("--resume", action="store_true", help="continue from <out>/checkpoints/last.pt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args):
    """The TrainConfig of the parsed options (``--version`` unset: the root's only table version)."""
    from occflownet.data.index import load_index
    from occflownet.train.recipe import TrainConfig

    version = args.version or load_index(args.dataroot, None, check_tables=False).version
    return TrainConfig(
        preset=args.preset, dataroot=str(args.dataroot), out=str(args.out), version=version, split=args.split,
        supervision=args.supervision, horizon=args.horizon, flow=args.flow, flow_mover=args.flow_mover,
        dynamic_filter=args.dynamic_filter, disocclusion=args.disocclusion, loss_weighting=args.loss_weighting,
        depth_loss=args.depth_loss, density_scale=args.density_scale, sigma_is=args.sigma_is,
        render_depth_weight=args.render_depth_weight, render_semantics=args.render_semantics,
        free_prior_weight=args.free_prior_weight, voxel_mask=args.voxel_mask,
        head_init=args.head_init, free_space=args.free_space, free_rays_per_step=args.free_rays_per_step,
        free_space_weight=args.free_space_weight,
        max_steps=args.max_steps, time_limit_s=args.time_limit,
        batch_size=args.batch_size, rays_per_step=args.rays_per_step, lr=args.lr,
        weight_decay=args.weight_decay, warmup_steps=args.warmup_steps, ema_decay=args.ema_decay,
        checkpoint_every=args.checkpoint_every, log_every=args.log_every, seed=args.seed,
        num_workers=args.num_workers, amp=not args.no_amp, device=args.device, threshold=args.threshold,
    )


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
