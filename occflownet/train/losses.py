"""Training losses: rendering (2D), LiDAR depth supervision of the LSS depth distribution, and 3D voxel labels.

Weights and definitions follow the paper and the official OccFlowNet code (docs/render.md):
- rendered depth: MSE per ray × ω(label), weight 0.05; rendered semantics: cross-entropy (softmax of the rendered
  logit mixture) per ray × ω(label), weight 1.0; both are the mean over rays of the weighted per-ray terms, as
  mmdet's ``weight_reduce_loss`` does in the official code. ω are the per-class weights from the data index
  (``occflownet.data.class_weights``: log(ΣN / N_c) normalised to mean 1), used as given; None = all ones;
- LiDAR depth (BEVDepth/BEVDet ``get_depth_loss``): the LiDAR points of the current frame are projected into the
  feature map of every camera; each feature pixel that receives points gets the one-hot of the depth bin
  nearest to its *closest* point; BCE between the predicted depth distribution and that one-hot, summed over
  bins and averaged over pixels with a target; weight 0.05;
- 3D (paper section 3.3): BCE on σ over all voxels (target occupied = label != 17), CE on the semantic logits of
  the occupied voxels, weight 1.0 each; an optional mask (e.g. ``mask_camera``) restricts both.

Weighted terms (the names the training log uses): ``ray_losses`` → "render_depth", "render_semantics";
``voxel_losses`` → "voxel_density", "voxel_semantics"; ``lidar_depth_loss`` × ``lidar_depth_weight`` →
"lidar_depth"; ``free_space_loss`` × ``free_space_weight`` → "free_space" (beyond the paper: LiDAR beams without a
return render through empty space).
Beyond the paper (options, docs/ablation.md): ``render_semantics="normalized"`` takes the CE of the rendered
mixture divided by its weight sum (the official CE on the raw mixture Σ w_i s_i also falls when the ray's opacity
grows anywhere along it, which rewards density in front of the surface); ``free_prior_weight`` > 0 adds
"free_prior": the mean over every voxel of -log(1 - σ), a pull towards free space for the voxels no ray reaches.
``total_loss`` combines the terms for the mode ``"2d"``, ``"3d"`` or ``"2d+3d"`` and adds their sum as "total".
``render_losses`` and ``lidar_depth_loss`` are the unweighted primitives.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from occflownet.choices import RENDER_SEMANTICS, SUPERVISION_MODES
from occflownet.occ3d import FREE, NUM_CLASSES

MODES = SUPERVISION_MODES


@dataclass(frozen=True)
class LossConfig:
    """Loss weights and the supervision mode; defaults are the official code's."""

    mode: str = "2d"                    # "2d" rendering, "3d" voxel labels, "2d+3d" both
    depth_weight: float = 0.05          # rendered depth MSE
    semantic_weight: float = 1.0        # rendered semantics CE
    lidar_depth_weight: float = 0.05    # BCE on the LSS depth distribution (0 disables it)
    voxel_density_weight: float = 1.0   # 3D: BCE on σ
    voxel_semantic_weight: float = 1.0  # 3D: CE on the logits of occupied voxels
    free_space_weight: float = 1.0      # free-space beams: BCE of their rendered opacity towards 0 (when given)
    render_semantics: str = "mixture"   # CE on the raw mixture (official) or on it ÷ weight sum ("normalized")
    free_prior_weight: float = 0.0      # mean -log(1 - σ) over all voxels (0 = off, the official setting)

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"LossConfig.mode must be one of {MODES}, got {self.mode!r}")
        if self.render_semantics not in RENDER_SEMANTICS:
            raise ValueError(f"LossConfig.render_semantics must be one of {RENDER_SEMANTICS}, "
                             f"got {self.render_semantics!r}")
        for name in ("depth_weight", "semantic_weight", "lidar_depth_weight", "voxel_density_weight",
                     "voxel_semantic_weight", "free_space_weight", "free_prior_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"LossConfig.{name} must be >= 0, got {getattr(self, name)}")


def _ray_weights(labels: torch.Tensor, class_weights: torch.Tensor | None, dtype) -> torch.Tensor:
    if class_weights is None:
        return torch.ones(labels.shape, dtype=dtype, device=labels.device)
    class_weights = torch.as_tensor(class_weights, dtype=dtype, device=labels.device)
    if class_weights.shape != (NUM_CLASSES,):
        raise ValueError(f"class_weights must be [{NUM_CLASSES}], got {tuple(class_weights.shape)}")
    return class_weights[labels]


def render_losses(depth: torch.Tensor, semantics: torch.Tensor, depth_gt: torch.Tensor, labels_gt: torch.Tensor,
                  class_weights: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Unweighted rendering losses → {"depth": mean ω·(d - d_gt)², "semantics": mean ω·CE}.

    depth [R] and semantics [R, 17] from ``render_rays``; depth_gt [R] metres along the ray (Euclidean distance
    from the camera centre, not z-depth); labels_gt [R] long Occ3D classes 0..16; class_weights [17] or None.
    With R = 0 both terms are 0 (and keep the graph).
    """
    if depth.dim() != 1 or semantics.shape != (depth.shape[0], NUM_CLASSES):
        raise ValueError(f"depth must be [R] and semantics [R, {NUM_CLASSES}], got {tuple(depth.shape)} and "
                         f"{tuple(semantics.shape)}")
    if depth_gt.shape != depth.shape or labels_gt.shape != depth.shape:
        raise ValueError(f"depth_gt and labels_gt must be [R] = [{depth.shape[0]}], got {tuple(depth_gt.shape)} and "
                         f"{tuple(labels_gt.shape)}")
    labels = labels_gt.long()
    if depth.shape[0] == 0:
        zero = depth.sum() + semantics.sum()
        return {"depth": zero, "semantics": zero}
    if int(labels.min()) < 0 or int(labels.max()) >= NUM_CLASSES:
        raise ValueError(f"labels_gt must lie in [0, {NUM_CLASSES}), got [{int(labels.min())}, {int(labels.max())}]")
    w = _ray_weights(labels, class_weights, depth.dtype)
    depth_term = (w * (depth - depth_gt.to(depth.dtype)) ** 2).mean()
    sem_term = (w * F.cross_entropy(semantics, labels, reduction="none")).mean()
    return {"depth": depth_term, "semantics": sem_term}


def ray_losses(rendered, depth_gt: torch.Tensor, labels_gt: torch.Tensor, class_weights: torch.Tensor | None = None,
               cfg: LossConfig = LossConfig()) -> dict[str, torch.Tensor]:
    """Weighted rendering terms {"render_depth": depth_weight · MSE, "render_semantics": semantic_weight · CE} for
    ``rendered`` (a ``RenderOutput``: depth [R], semantics [R, 17], weight_sum [R]); see ``render_losses``."""
    semantics = rendered.semantics
    if cfg.render_semantics == "normalized":  # the logits the ray sees, whatever share of its light stops
        semantics = semantics / rendered.weight_sum.clamp(min=1e-4).unsqueeze(-1)
    r = render_losses(rendered.depth, semantics, depth_gt, labels_gt, class_weights)
    return {"render_depth": cfg.depth_weight * r["depth"], "render_semantics": cfg.semantic_weight * r["semantics"]}


def free_space_loss(opacity: torch.Tensor) -> torch.Tensor:
    """Unweighted free-space term: mean over beams of -log(1 - opacity), opacity [F] = the rendered weight sum
    Σ w_i of LiDAR beams that returned nothing (``occflownet.data.free_space``): 0 when the grid lets them pass,
    growing without bound as a beam is stopped (clamped at opacity 1 - 1e-4). F = 0 gives 0 (graph kept)."""
    if opacity.dim() != 1:
        raise ValueError(f"opacity must be [F], got {tuple(opacity.shape)}")
    if opacity.shape[0] == 0:
        return opacity.sum()
    return -torch.log1p(-opacity.clamp(0.0, 1.0 - 1e-4)).mean()


def free_prior_loss(density: torch.Tensor) -> torch.Tensor:
    """Unweighted free prior: mean over all voxels of -log(1 - σ), density [B, X, Y, Z] in [0, 1] (clamped at
    1 - 1e-4). With ``sigma_is="opacity"`` it is each voxel's optical depth, so it charges every voxel by how much
    light it would stop; the rays' terms outweigh it where rays go. The same -log(1 - x) as ``free_space_loss``,
    over voxels instead of beams."""
    with torch.autocast(device_type=density.device.type, enabled=False):
        return free_space_loss(density.float().reshape(-1))


def lidar_depth_targets(feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                        points_ego: Sequence[torch.Tensor], feature_size: tuple[int, int],
                        depth_bin_centers: torch.Tensor) -> torch.Tensor:
    """Depth-bin targets of the feature maps → long [B, N_cam, h, w]: bin index, or -1 where no point lands.

    feature_intrinsics [B, N, 3, 3]: camera frame (OpenCV) → feature-map pixels, pixel centres at integer
    coordinates (for stride s: fx/s, fy/s, (cx + 0.5)/s - 0.5, (cy + 0.5)/s - 0.5); a point lands in feature
    pixel (round(u), round(v)). cam2ego [B, N, 4, 4]. points_ego: B tensors [N_b, 3], LiDAR points of the
    current frame in the ego frame. The depth is the camera z-depth (the LSS frustum's depth); the target of a
    pixel is the bin whose centre is nearest to the smallest depth among its points; depths more than half a
    bin outside [centers[0], centers[-1]] give no target.
    """
    b, n_cam = feature_intrinsics.shape[:2]
    h, w = feature_size
    if cam2ego.shape != (b, n_cam, 4, 4) or feature_intrinsics.shape != (b, n_cam, 3, 3):
        raise ValueError(f"feature_intrinsics must be [B, N, 3, 3] and cam2ego [B, N, 4, 4], got "
                         f"{tuple(feature_intrinsics.shape)} and {tuple(cam2ego.shape)}")
    if len(points_ego) != b:
        raise ValueError(f"points_ego must hold {b} tensors (one per batch item), got {len(points_ego)}")
    centers = depth_bin_centers.to(torch.float64)
    if centers.dim() != 1 or centers.numel() < 2 or not bool((centers[1:] > centers[:-1]).all()):
        raise ValueError("depth_bin_centers must be an increasing 1-D tensor with at least 2 bins")
    device = feature_intrinsics.device
    nearest = torch.full((b * n_cam * h * w,), float("inf"), dtype=torch.float64, device=device)
    ego2cam = torch.linalg.inv(cam2ego.to(torch.float64))
    k = feature_intrinsics.to(torch.float64)
    for bi, pts in enumerate(points_ego):
        if pts.dim() != 2 or pts.shape[1] < 3:
            raise ValueError(f"points_ego[{bi}] must be [N, 3], got {tuple(pts.shape)}")
        p = pts[:, :3].to(device=device, dtype=torch.float64)
        for ci in range(n_cam):
            cam = p @ ego2cam[bi, ci, :3, :3].T + ego2cam[bi, ci, :3, 3]
            z = cam[:, 2]
            front = z > 1e-6
            uvw = cam[front] @ k[bi, ci].T
            col = torch.round(uvw[:, 0] / uvw[:, 2])
            row = torch.round(uvw[:, 1] / uvw[:, 2])
            ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
            flat = ((bi * n_cam + ci) * h + row[ok].long()) * w + col[ok].long()
            nearest.scatter_reduce_(0, flat, z[front][ok], reduce="amin")
    half_lo = 0.5 * (centers[1] - centers[0])
    half_hi = 0.5 * (centers[-1] - centers[-2])
    valid = (nearest >= centers[0] - half_lo) & (nearest <= centers[-1] + half_hi)
    boundaries = 0.5 * (centers[1:] + centers[:-1])
    bins = torch.bucketize(nearest.clamp(max=float(centers[-1]) + 1.0), boundaries)
    return torch.where(valid, bins, torch.full_like(bins, -1)).view(b, n_cam, h, w)


def lidar_depth_loss(depth_prob: torch.Tensor, feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                     points_ego: Sequence[torch.Tensor], depth_bin_centers: torch.Tensor) -> torch.Tensor:
    """BCE between the LSS depth distribution depth_prob [B, N, D, h, w] (probabilities over D) and one-hot
    LiDAR targets (``lidar_depth_targets``): summed over the D bins, averaged over pixels with a target
    (0 when no pixel has one). Unweighted (``LossConfig.lidar_depth_weight`` is applied by ``total_loss``)."""
    if depth_prob.dim() != 5 or depth_prob.shape[2] != depth_bin_centers.numel():
        raise ValueError(f"depth_prob must be [B, N, D, h, w] with D = {depth_bin_centers.numel()} bins, got "
                         f"{tuple(depth_prob.shape)}")
    b, n_cam, d, h, w = depth_prob.shape
    with torch.no_grad():
        target_bins = lidar_depth_targets(feature_intrinsics, cam2ego, points_ego, (h, w), depth_bin_centers)
    has_target = target_bins >= 0  # [B, N, h, w]
    n_target = int(has_target.sum())
    if n_target == 0:
        return depth_prob.sum() * 0.0
    pred = depth_prob.permute(0, 1, 3, 4, 2)[has_target]  # [P, D]
    onehot = F.one_hot(target_bins[has_target], d).to(pred.dtype)
    with torch.autocast(device_type=pred.device.type, enabled=False):
        bce = F.binary_cross_entropy(pred.float(), onehot.float(), reduction="sum")
    return bce / n_target


def voxel_losses(density: torch.Tensor, logits: torch.Tensor, semantics_gt: torch.Tensor,
                 mask: torch.Tensor | None = None, cfg: LossConfig = LossConfig()) -> dict[str, torch.Tensor]:
    """3D supervision → {"voxel_density": voxel_density_weight · BCE(σ, gt != 17) mean over the (masked) voxels,
    "voxel_semantics": voxel_semantic_weight · CE over the occupied (masked) voxels} (both weights 1 by default).
    density [B, X, Y, Z] in [0, 1]; logits [B, X, Y, Z, 17]; semantics_gt uint8/long [B, X, Y, Z] with
    17 = free; mask bool [B, X, Y, Z] or None (all voxels; the official 3D training uses no mask)."""
    if logits.shape[:-1] != density.shape or logits.shape[-1] != NUM_CLASSES:
        raise ValueError(f"logits must be density's shape {tuple(density.shape)} + [{NUM_CLASSES}], got "
                         f"{tuple(logits.shape)}")
    if semantics_gt.shape != density.shape:
        raise ValueError(f"semantics_gt must be {tuple(density.shape)}, got {tuple(semantics_gt.shape)}")
    labels = semantics_gt.long()
    if int(labels.min()) < 0 or int(labels.max()) > FREE:
        raise ValueError(f"semantics_gt values must lie in [0, {FREE}]")
    occupied = labels != FREE
    if mask is not None:
        if mask.shape != density.shape:
            raise ValueError(f"mask must be {tuple(density.shape)}, got {tuple(mask.shape)}")
        keep = mask.bool()
    else:
        keep = torch.ones_like(occupied)
    with torch.autocast(device_type=density.device.type, enabled=False):
        sigma = density[keep].float()
        density_term = F.binary_cross_entropy(sigma, occupied[keep].float()) if sigma.numel() else density.sum() * 0
    sem_keep = keep & occupied
    if bool(sem_keep.any()):
        semantic_term = F.cross_entropy(logits[sem_keep], labels[sem_keep])
    else:
        semantic_term = logits.sum() * 0.0
    return {"voxel_density": cfg.voxel_density_weight * density_term,
            "voxel_semantics": cfg.voxel_semantic_weight * semantic_term}


def _require(what: str, **inputs) -> None:
    """ValueError naming the inputs ``what`` needs that are None."""
    missing = [name for name, value in inputs.items() if value is None]
    if missing:
        raise ValueError(f"{what} needs {', '.join(missing)}")


def total_loss(cfg: LossConfig, *, rendered=None, depth_gt=None, labels_gt=None, class_weights=None,
               depth_prob=None, feature_intrinsics=None, cam2ego=None, points_ego=None, depth_bin_centers=None,
               density=None, logits=None, semantics_gt=None, voxel_mask=None,
               free_opacity=None, before_opacity=None, prior_density=None) -> dict[str, torch.Tensor]:
    """Weighted loss terms of the configured mode plus their sum under "total".

    2D terms (modes "2d", "2d+3d"): ``rendered`` (a ``RenderOutput``), ``depth_gt`` [R], ``labels_gt`` [R],
    ``class_weights`` [17] or None → "render_depth", "render_semantics". 3D terms (modes "3d", "2d+3d"):
    ``density``, ``logits``, ``semantics_gt``, ``voxel_mask`` → "voxel_density", "voxel_semantics". LiDAR depth
    (any mode, when ``lidar_depth_weight`` > 0 and ``depth_prob`` is given): "lidar_depth". Free-space beams (any
    mode, when ``free_opacity`` [F] is given): "free_space"; the free stretches in front of the rays' points
    (``before_opacity`` [S]): "free_before", the same loss and weight. Free prior (any mode, when ``free_prior_weight`` > 0:
    ``prior_density`` [B, X, Y, Z] is required): "free_prior". Every term is already
    multiplied by its weight. A missing input the mode needs raises ValueError naming it.
    """
    terms: dict[str, torch.Tensor] = {}
    if cfg.mode in ("2d", "2d+3d"):
        _require(f"total_loss mode {cfg.mode!r}", rendered=rendered, depth_gt=depth_gt, labels_gt=labels_gt)
        terms.update(ray_losses(rendered, depth_gt, labels_gt, class_weights, cfg))
    if cfg.mode in ("3d", "2d+3d"):
        _require(f"total_loss mode {cfg.mode!r}", density=density, logits=logits, semantics_gt=semantics_gt)
        terms.update(voxel_losses(density, logits, semantics_gt, voxel_mask, cfg))
    if cfg.lidar_depth_weight > 0 and depth_prob is not None:
        _require("lidar depth loss (with depth_prob)", feature_intrinsics=feature_intrinsics, cam2ego=cam2ego,
                 points_ego=points_ego, depth_bin_centers=depth_bin_centers)
        terms["lidar_depth"] = cfg.lidar_depth_weight * lidar_depth_loss(
            depth_prob, feature_intrinsics, cam2ego, points_ego, depth_bin_centers)
    if free_opacity is not None and cfg.free_space_weight > 0:
        terms["free_space"] = cfg.free_space_weight * free_space_loss(free_opacity)
    if before_opacity is not None and cfg.free_space_weight > 0:
        terms["free_before"] = cfg.free_space_weight * free_space_loss(before_opacity)
    if cfg.free_prior_weight > 0:
        _require("free prior (free_prior_weight > 0)", prior_density=prior_density)
        terms["free_prior"] = cfg.free_prior_weight * free_prior_loss(prior_density)
    if not terms:
        raise ValueError("total_loss produced no term: check LossConfig.mode and the inputs")
    terms["total"] = sum(terms.values())
    return terms
