"""`occflownet view`: write one self-contained HTML file that shows a grid in 3D (three.js, WebGL): coloured cubes
with the Occ3D legend and per-class toggles, orbit/zoom, the ego vehicle and the six camera frusta; the ground truth
beside it with ``--gt`` (its ``mask_camera`` can hide what eval does not score); the camera images as thumbnails
with ``--images``. The file needs no network: its script and data are inside it (:mod:`occflownet.viewer`).

Grids: ``predict``'s .npz, ``eval --save-predictions`` .npz files, the server's or the C++ program's .npy, raw
octet-stream bytes, or an Occ3D ``labels.npz`` (then shown as the ground truth).

The options are the grid, the fields of :class:`occflownet.viewer.ViewConfig` (``occflownet/options.py``) and
``--out``."""
import sys

from occflownet.options import add_options, config_kwargs
from occflownet.viewer import ViewConfig

HELP = "write an interactive 3D viewer (one HTML file) of a grid, optionally beside its ground truth"


def add_arguments(p):
    p.add_argument("grid", help="grid file: .npz (predict, eval --save-predictions, Occ3D labels), .npy, raw bytes")
    add_options(p, ViewConfig)
    p.add_argument("--out", required=True, help="output .html")


def run(args) -> int:
    from pathlib import Path

    from occflownet import contract, viewer
    from occflownet.predict import find_camera_images

    cfg = ViewConfig(**config_kwargs(args, ViewConfig))
    try:
        grids = [viewer.read_grid(args.grid)]
        if cfg.gt:
            grids.insert(0, viewer.read_grid(cfg.gt, "ground truth"))
        calib = contract.load_calibration(cfg.calib) if cfg.calib else None
        images = {cam: p.read_bytes() for cam, p in find_camera_images(cfg.images).items()} if cfg.images else None
        title = cfg.title or Path(args.grid).name
        files = [cfg.gt, args.grid] if cfg.gt else [args.grid]                 # in the order of `grids`
        subtitle = " · ".join(f"{g.name}: {Path(f).name}" for g, f in zip(grids, files))
        out = viewer.write_viewer(args.out, grids, calib, images, title=title, subtitle=subtitle)
    except (FileNotFoundError, ValueError, OSError) as exc:
        print(f"occflownet view: {exc}", file=sys.stderr)
        return 1
    counts = ", ".join(f"{g.name} {int((g.occupancy != 17).sum())} occupied voxels" for g in grids)
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB: {counts}); open it in a browser, no network needed")
    return 0
