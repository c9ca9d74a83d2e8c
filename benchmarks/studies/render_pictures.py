"""What a trained model renders, beside the LiDAR labels it was trained on (docs/results.md): for one keyframe and one
camera, the rendered depth, opacity and semantics through every ``--step``-th pixel, and the LiDAR points of that
camera (their depth and class), plus the per-ray figures at the LiDAR pixels (the training rays of t = 0).

    python -m benchmarks.studies.render_pictures --run RUN --dataroot W [--sample 0] [--camera 0] [--out render.png]

RUN is a training run folder (``checkpoints/last.pt`` and ``train_config.json``: the rendering reads σ as the run
did, ``sigma_is``). The picture: top row camera image | LiDAR depth | rendered depth (Σ w t ÷ Σ w, where Σ w > 0.05);
bottom row rendered opacity Σ w | LiDAR classes | rendered classes (argmax of Σ w s, where Σ w > 0.05). Depths
share one colour scale (0 to 40 m, turbo). Printed: at the LiDAR pixels, the median and mean absolute depth error
(Σ w t against the LiDAR distance, as the depth loss sees it, and Σ w t ÷ Σ w), the median opacity and the share of
rays whose rendered class is the LiDAR class.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from occflownet.data.index import load_index
from occflownet.data.loaders import load_sample_images
from occflownet.data.rays import frame_hits
from occflownet.eval.picture import _fit, _label
from occflownet.model.checkpoint import load_checkpoint
from occflownet.occ3d import CAMERAS, CLASS_COLORS
from occflownet.pictures import class_legend, save_png
from occflownet.render.volume_render import RenderConfig, render_rays

FAR = 40.0
MIN_OPACITY = 0.05


def _pixel_rays(pixels: np.ndarray, intrinsic: np.ndarray, cam2ego: np.ndarray):
    """Pixel coordinates [P, 2] → (origins [P, 3], unit directions [P, 3]) in the ego frame of the keyframe."""
    rays = np.concatenate([pixels, np.ones((len(pixels), 1))], 1) @ np.linalg.inv(intrinsic).T
    dirs = rays @ cam2ego[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.repeat(cam2ego[None, :3, 3], len(pixels), 0), dirs


def _render(density, logits, origins, dirs, cfg: RenderConfig, chunk: int = 16384):
    """Rendered (depth Σ w t [P], opacity Σ w [P], class argmax [P]) of rays [P, 3] in chunks."""
    depth, opacity, cls = [], [], []
    for s in range(0, len(origins), chunk):
        out = render_rays(density, logits, torch.from_numpy(origins[s:s + chunk]).float(),
                          torch.from_numpy(dirs[s:s + chunk]).float(), cfg, torch.Generator().manual_seed(0))
        depth.append(out.depth.numpy())
        opacity.append(out.weight_sum.numpy())
        cls.append(out.semantics.argmax(-1).numpy())
    return np.concatenate(depth), np.concatenate(opacity), np.concatenate(cls)


def _depth_rgb(depth: np.ndarray) -> np.ndarray:
    import cv2

    scaled = np.clip(depth / FAR * 255, 0, 255).astype(np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)[:, 0, ::-1]


def picture(run: Path, dataroot: Path, sample_pos: int, camera: int, step: int):
    """(picture uint8 [H', W', 3], figures dict) of keyframe ``sample_pos`` of ``dataroot``, camera ``camera``."""
    train_cfg = json.loads((run / "train_config.json").read_text())
    model, _, _ = load_checkpoint(run / "checkpoints" / "last.pt")
    index = load_index(dataroot, None, check_tables=False)
    sample = index[sample_pos]
    images = load_sample_images(dataroot, sample)
    K = np.asarray(sample.intrinsics[camera], np.float64)
    T = np.asarray(sample.cam2current_ego()[camera], np.float64)
    with torch.inference_mode():
        out = model(torch.from_numpy(images[None]), torch.from_numpy(sample.intrinsics[None]).float(),
                    torch.from_numpy(sample.cam2current_ego()[None]).float())
    density, logits = out["density"][0].float(), out["logits"][0].float()
    cfg = RenderConfig(density_scale=train_cfg.get("density_scale", 1.0),
                       sigma_is=train_cfg.get("sigma_is", "density"))
    h, w = images.shape[1:3]
    v, u = np.mgrid[0:h - step + 1:step, 0:w - step + 1:step]
    grid_px = np.stack([u + 0.5 * step, v + 0.5 * step], -1).reshape(-1, 2).astype(np.float64)
    depth, opacity, cls = _render(density, logits, *_pixel_rays(grid_px, K, T), cfg)
    shown = opacity > MIN_OPACITY
    mean_depth = np.where(shown, depth / np.maximum(opacity, 1e-6), 0.0)
    shape = v.shape + (3,)
    rendered_depth = np.where(shown[:, None], _depth_rgb(mean_depth), 0).reshape(shape)
    rendered_cls = np.where(shown[:, None], CLASS_COLORS[cls], 0).reshape(shape)
    gray = (np.clip(opacity, 0, 1) * 255).astype(np.uint8)
    rendered_opacity = np.repeat(gray[:, None], 3, 1).reshape(shape)

    hits = frame_hits(sample, dataroot)
    mine = hits.cameras == camera
    px, lidar_depth, labels = hits.pixels[mine].astype(np.float64), hits.depths[mine], hits.labels[mine]
    d_hit, o_hit, c_hit = _render(density, logits, *_pixel_rays(px, K, T), cfg)
    lidar_depth_img = np.zeros(shape, np.uint8)
    lidar_cls_img = np.zeros(shape, np.uint8)
    rows = np.clip((px[:, 1] / step).astype(int), 0, shape[0] - 1)
    cols = np.clip((px[:, 0] / step).astype(int), 0, shape[1] - 1)
    lidar_depth_img[rows, cols] = _depth_rgb(lidar_depth)
    lidar_cls_img[rows, cols] = CLASS_COLORS[labels]
    camera_img = images[camera][v, u]
    name = CAMERAS[camera]
    panel = 2 * v.shape[1]
    top = [_label(_fit(camera_img, panel), name), _label(_fit(lidar_depth_img, panel), "LiDAR depth"),
           _label(_fit(rendered_depth, panel), "rendered depth")]
    bottom = [_label(_fit(rendered_opacity, panel), "rendered opacity"),
              _label(_fit(lidar_cls_img, panel), "LiDAR classes"), _label(_fit(rendered_cls, panel), "rendered classes")]
    img = np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0)
    img = np.concatenate([img, class_legend(img.shape[1])], 0)
    normalised = d_hit / np.maximum(o_hit, 1e-6)
    figures = {"camera": name, "lidar_rays": int(mine.sum()), "sigma_is": cfg.sigma_is,
               "depth_error_median_m": float(np.median(d_hit - lidar_depth)),
               "depth_abs_error_mean_m": float(np.mean(np.abs(d_hit - lidar_depth))),
               "normalised_depth_error_median_m": float(np.median(normalised - lidar_depth)),
               "opacity_median": float(np.median(o_hit)),
               "class_agreement": float(np.mean(c_hit == labels)),
               "pixels_opaque_share": float(np.mean(opacity > 0.5))}
    return img, figures


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--dataroot", required=True, type=Path)
    ap.add_argument("--sample", type=int, default=0, help="position of the keyframe in the root's index")
    ap.add_argument("--camera", type=int, default=0, help="index in occ3d.CAMERAS (0 = CAM_FRONT)")
    ap.add_argument("--step", type=int, default=2, help="render every step-th pixel")
    ap.add_argument("--out", type=Path, default=Path("render.png"))
    args = ap.parse_args()
    img, figures = picture(args.run, args.dataroot, args.sample, args.camera, args.step)
    save_png(args.out, img)
    print(json.dumps(figures, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
