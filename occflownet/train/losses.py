"""Training losses: the weighted terms of a run, chosen once from its :class:`TrainConfig`, and their functions.

:func:`loss_terms` reads the configuration and returns the run's terms, each a :class:`LossTerm`: the name the
training log uses, its weight, the inputs it needs, and the unweighted function of those inputs. The inputs are named
as :class:`occflownet.train.step.LossComputer` provides them (it computes only those its terms name): batch fields
(``ray_depths``, ``ray_labels``, ``cam2ego``, ``depth_points``, ``depth_labels``, and :func:`voxel_targets`'
``voxel_occupied``, ``voxel_classes``, ``occupied_labels``), model outputs (``density``, ``logits``, ``depth_prob``,
``feature_intrinsics``, ``image_logits``; ``voxel_sigma`` and ``kept_logits``: σ and the logits at the supervised
voxels, ``occupied_logits`` at the occupied ones among them), renderings through the per-frame volumes
(``rendered``, the ``RenderOutput`` of the batch's rays; ``free_opacity``; ``before_opacity``) and constants
(``class_weights``, ``depth_bins``). The loss is the sum of the weighted terms, in this order:

- "render_depth" (2D supervision): MSE of the rendered depth per ray × ω(label), weight ``render_depth_weight``
  (0.05, official; 0 without ``depth_loss``, the "semantics only" row, which still logs the term);
- "render_semantics" (2D): cross-entropy of the rendered logit mixture per ray × ω(label), weight 1.0; both are
  the mean over rays of the weighted per-ray terms, as mmdet's ``weight_reduce_loss`` does in the official code.
  ω are the per-class weights from the data index (``occflownet.data.class_weights``: log(ΣN / N_c) normalised to
  mean 1), used as given (``loss_weighting``); without, all ones;
- "point_semantics" (``point_semantics_weight`` > 0, beyond the paper): mean over the rays whose LiDAR point lies
  in the grid of ω(label)·CE(logits of the voxel holding the point, in the ray's frame volume; label), weight
  ``point_semantics_weight``: the rendered mixture spreads a ray that grazes the ground over metres of voxels, so
  neighbouring rays of two classes blur their boundary; this term names the one voxel each label belongs to;
- "point_density" (``point_density_weight`` > 0, beyond the paper): mean over the same points of -log σ of the voxel
  holding the point (in the ray's frame volume), weight ``point_density_weight``: with σ ≤ 1 per metre the rendered
  depth is met by light spread over metres around the point, leaving the labelled voxel itself half dense;
- "voxel_density", "voxel_semantics" (3D supervision, paper section 3.3): BCE on σ over all voxels (target
  occupied = label != 17) and CE on the semantic logits of the occupied voxels, weight 1.0 each; with
  ``voxel_mask`` both only inside ``mask_camera`` (:func:`voxel_targets` says which voxels);
- "voxel_scal" (``voxel_scal_weight`` > 0, with 3D labels; beyond the paper): MonoScene's scene-class affinity
  terms over the same voxels: −log of the precision, recall and specificity of the soft occupancy σ against
  label != 17, plus the mean over the classes c labelled in the batch of the same three for σ·softmax(logits)_c
  against label == c (:func:`voxel_scal_loss`); the semantic head then runs on every supervised voxel;
- "lidar_depth" (``depth_loss``; BEVDepth/BEVDet ``get_depth_loss``): the LiDAR points of the current frame are
  projected into the feature map of every camera; each feature pixel that receives points gets the one-hot of the
  depth bin nearest to its *closest* point; BCE between the predicted depth distribution and that one-hot, summed
  over bins and averaged over pixels with a target; weight ``lidar_depth_weight`` (0.05, official);
- "image_semantics" (``image_semantics_weight`` > 0, beyond the paper): the same points' labels; cross-entropy of
  the model's image head (``ModelConfig.image_semantics``: the class of each feature cell, training only) against
  the label of each feature pixel's closest point, averaged over those pixels (:func:`image_semantics_loss`): the
  image features learn the classes directly, not only through the lift;
- "free_space" (``free_space`` or ``free_beyond_grid``, beyond the paper): mean -log(1 - opacity) of the free rays
  (LiDAR beams without a return, camera rays to points beyond the grid), weight ``free_space_weight`` (none at 0),
  raised linearly from 0 over the first ``free_ramp_steps`` steps when that is set;
- "free_before" (``free_before_point``, beyond the paper): the same loss and weight over the free stretches in
  front of the rays' points (the same ramp);
- "free_prior" (``free_prior_weight`` > 0, beyond the paper): mean over every voxel of -log(1 - σ), a pull towards
  free space for the voxels no ray reaches.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from occflownet.choices import supervision_parts
from occflownet.occ3d import FREE, NUM_CLASSES
from occflownet.train.recipe import TrainConfig

SEMANTIC_WEIGHT = 1.0      # rendered semantics CE (official)
VOXEL_WEIGHT = 1.0         # each of the two 3D terms (paper section 3.3)


@dataclass(frozen=True)
class LossTerm:
    """One weighted term of the training loss, logged as ``name``: ``weight · ramp(step) · fn(*inputs)``, the inputs
    named by ``needs`` in the order ``fn`` takes them; ramp(step) = min(1, step / ramp_steps) (1 when ramp_steps is
    0 or no step is given)."""

    name: str
    weight: float
    needs: tuple[str, ...]
    fn: Callable[..., torch.Tensor]
    ramp_steps: int = 0

    def __call__(self, inputs: Mapping[str, Any], step: int | None = None) -> torch.Tensor:
        """The weighted term (a scalar tensor) of ``inputs``, which maps at least every name of ``needs``, at
        optimisation step ``step`` (counted from 0)."""
        return self.weight * self.ramp(step) * self.fn(*(inputs[name] for name in self.needs))

    def ramp(self, step: int | None) -> float:
        return 1.0 if self.ramp_steps <= 0 or step is None else min(1.0, step / self.ramp_steps)


# What a step must load and check for each input a term names: the one table from which the data pipeline
# (``dataset.TrainingSamples``), the data checks before training (``loop``) and the step's work counts follow.
# "rays": the LiDAR rays of frames t in [-O, O] (and, with flow, the boxes' moves); "free_rays": LiDAR beams without
# a return and camera rays beyond the grid; "depth_points": the keyframe's LiDAR points; "voxel_labels": the Occ3D
# labels (``gts/``); "class_counts": prepare's per-class ray counts (the weights ω). Inputs not listed come from the
# model or are constants.
INPUT_DATA: dict[str, tuple[str, ...]] = {
    "rendered": ("rays",), "ray_depths": ("rays",), "ray_labels": ("rays",), "point_logits": ("rays",),
    "point_labels": ("rays",), "point_sigma": ("rays",), "before_opacity": ("rays",),
    "free_opacity": ("rays", "free_rays"),
    "voxel_sigma": ("voxel_labels",), "voxel_occupied": ("voxel_labels",), "occupied_logits": ("voxel_labels",),
    "occupied_labels": ("voxel_labels",), "kept_logits": ("voxel_labels",), "voxel_classes": ("voxel_labels",),
    "depth_points": ("depth_points",), "depth_labels": ("depth_points",), "class_weights": ("class_counts",),
}


def loss_terms(cfg: TrainConfig) -> tuple[LossTerm, ...]:
    """The terms of a run (see the module docstring), in the order the log lists them and the loss sums them. The
    only place a run's supervision and its loss options are read: everything a step loads follows from the terms
    (:func:`step_data`)."""
    weights = ("class_weights",) if cfg.loss_weighting else ()
    rays = ("rendered", "ray_depths", "ray_labels", *weights)
    parts = supervision_parts(cfg.supervision)
    two_d, three_d = "2d" in parts, "3d" in parts
    terms = []
    if two_d:
        terms += [LossTerm("render_depth", cfg.render_depth_weight if cfg.depth_loss else 0.0, rays,
                           render_depth_loss),
                  LossTerm("render_semantics", SEMANTIC_WEIGHT, ("rendered", "ray_labels", *weights),
                           render_semantics_loss)]
    if cfg.point_semantics_weight > 0:
        terms.append(LossTerm("point_semantics", cfg.point_semantics_weight,
                              ("point_logits", "point_labels", *weights), point_semantics_loss))
    if cfg.point_density_weight > 0:
        terms.append(LossTerm("point_density", cfg.point_density_weight, ("point_sigma",), point_density_loss))
    if three_d:
        terms += [LossTerm("voxel_density", VOXEL_WEIGHT, ("voxel_sigma", "voxel_occupied"), voxel_density_loss),
                  LossTerm("voxel_semantics", VOXEL_WEIGHT, ("occupied_logits", "occupied_labels"),
                           voxel_semantics_loss)]
        if cfg.voxel_scal_weight > 0:
            terms.append(LossTerm("voxel_scal", cfg.voxel_scal_weight,
                                  ("voxel_sigma", "kept_logits", "voxel_classes"), voxel_scal_loss))
    if cfg.depth_loss:
        terms.append(LossTerm("lidar_depth", cfg.lidar_depth_weight,
                              ("depth_prob", "feature_intrinsics", "cam2ego", "depth_points", "depth_bins"),
                              lidar_depth_loss))
    if cfg.image_semantics_weight > 0:
        terms.append(LossTerm("image_semantics", cfg.image_semantics_weight,
                              ("image_logits", "feature_intrinsics", "cam2ego", "depth_points", "depth_labels"),
                              image_semantics_loss))
    if (cfg.free_space or cfg.free_beyond_grid) and cfg.free_space_weight > 0:
        terms.append(LossTerm("free_space", cfg.free_space_weight, ("free_opacity",), free_space_loss,
                              cfg.free_ramp_steps))
    if cfg.free_before_point and cfg.free_space_weight > 0:
        terms.append(LossTerm("free_before", cfg.free_space_weight, ("before_opacity",), free_space_loss,
                              cfg.free_ramp_steps))
    if cfg.free_prior_weight > 0:
        terms.append(LossTerm("free_prior", cfg.free_prior_weight, ("density",), free_prior_loss))
    return tuple(terms)


def step_data(terms: Sequence[LossTerm]) -> frozenset[str]:
    """The data a step of ``terms`` loads (the kinds of :data:`INPUT_DATA`: "rays", "free_rays", "depth_points",
    "voxel_labels", "class_counts")."""
    return frozenset(kind for term in terms for name in term.needs for kind in INPUT_DATA.get(name, ()))


# --- the rendered rays --------------------------------------------------------------------------------------------

def _ray_labels(rendered, labels_gt: torch.Tensor) -> torch.Tensor:
    """labels_gt [R] as long, checked against ``rendered`` (depth [R], semantics [R, 17])."""
    depth, semantics = rendered.depth, rendered.semantics
    if depth.dim() != 1 or semantics.shape != (depth.shape[0], NUM_CLASSES):
        raise ValueError(f"rendered depth must be [R] and semantics [R, {NUM_CLASSES}], got {tuple(depth.shape)} "
                         f"and {tuple(semantics.shape)}")
    if labels_gt.shape != depth.shape:
        raise ValueError(f"labels_gt must be [R] = [{depth.shape[0]}], got {tuple(labels_gt.shape)}")
    labels = labels_gt.long()
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= NUM_CLASSES):
        raise ValueError(f"labels_gt must lie in [0, {NUM_CLASSES}), got [{int(labels.min())}, {int(labels.max())}]")
    return labels


def _ray_weights(labels: torch.Tensor, class_weights: torch.Tensor | None, dtype) -> torch.Tensor:
    """ω(label) [R] from class_weights [17] (None: ones)."""
    if class_weights is None:
        return torch.ones(labels.shape, dtype=dtype, device=labels.device)
    class_weights = torch.as_tensor(class_weights, dtype=dtype, device=labels.device)
    if class_weights.shape != (NUM_CLASSES,):
        raise ValueError(f"class_weights must be [{NUM_CLASSES}], got {tuple(class_weights.shape)}")
    return class_weights[labels]


def render_depth_loss(rendered, depth_gt: torch.Tensor, labels_gt: torch.Tensor,
                      class_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rays of ω(label)·(d − d_gt)², unweighted. ``rendered``: a ``RenderOutput`` (depth [R],
    semantics [R, 17]); depth_gt [R] metres along the ray (distance from the camera centre, not z-depth);
    labels_gt [R] Occ3D classes 0..16; class_weights [17] or None. R = 0 gives 0 (graph kept)."""
    labels = _ray_labels(rendered, labels_gt)
    depth = rendered.depth
    if depth_gt.shape != depth.shape:
        raise ValueError(f"depth_gt must be [R] = [{depth.shape[0]}], got {tuple(depth_gt.shape)}")
    if depth.shape[0] == 0:
        return depth.sum()
    w = _ray_weights(labels, class_weights, depth.dtype)
    return (w * (depth - depth_gt.to(depth.dtype)) ** 2).mean()


def _semantics_ce(semantics: torch.Tensor, labels: torch.Tensor, class_weights: torch.Tensor | None) -> torch.Tensor:
    """Mean over rays of ω(label)·CE(semantics [R, 17], labels [R]); R = 0 gives 0 (graph kept)."""
    if semantics.shape[0] == 0:
        return semantics.sum()
    w = _ray_weights(labels, class_weights, semantics.dtype)
    return (w * F.cross_entropy(semantics, labels, reduction="none")).mean()


def render_semantics_loss(rendered, labels_gt: torch.Tensor,
                          class_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rays of ω(label)·CE of the rendered logit mixture Σ w_i s_i (``rendered.semantics`` [R, 17], the
    official term), unweighted; labels_gt [R], class_weights [17] or None."""
    return _semantics_ce(rendered.semantics, _ray_labels(rendered, labels_gt), class_weights)


def point_semantics_loss(point_logits: torch.Tensor, point_labels: torch.Tensor,
                         class_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over points of ω(label)·CE(point_logits [P, 17], point_labels [P] 0..16), unweighted: the logits of the
    voxel holding each ray's LiDAR point (``LossComputer.point_values``). P = 0 gives 0 (graph kept)."""
    if point_logits.dim() != 2 or point_logits.shape[1] != NUM_CLASSES or point_labels.shape != point_logits.shape[:1]:
        raise ValueError(f"point_logits must be [P, {NUM_CLASSES}] and point_labels [P], got "
                         f"{tuple(point_logits.shape)} and {tuple(point_labels.shape)}")
    return _semantics_ce(point_logits, point_labels.long(), class_weights)


def point_density_loss(point_sigma: torch.Tensor) -> torch.Tensor:
    """Mean over points of -log σ (clamped at 1e-4), point_sigma [P] in [0, 1]: σ of the voxel holding each ray's
    LiDAR point (``LossComputer.point_values``), unweighted. P = 0 gives 0 (graph kept)."""
    if point_sigma.dim() != 1:
        raise ValueError(f"point_sigma must be [P], got {tuple(point_sigma.shape)}")
    if point_sigma.shape[0] == 0:
        return point_sigma.sum()
    return -torch.log(point_sigma.clamp(min=1e-4)).mean()


def free_space_loss(opacity: torch.Tensor) -> torch.Tensor:
    """Unweighted free-space term: mean over beams of -log(1 - opacity), opacity [F] = the rendered weight sum
    Σ w_i of LiDAR beams that returned nothing (``occflownet.data.free_space``): 0 when the grid lets them pass,
    growing without bound as a beam is stopped (clamped at opacity 1 - 1e-4). F = 0 gives 0 (graph kept)."""
    if opacity.dim() != 1:
        raise ValueError(f"opacity must be [F], got {tuple(opacity.shape)}")
    if opacity.shape[0] == 0:
        return opacity.sum()
    return -torch.log1p(-opacity.clamp(0.0, 1.0 - 1e-4)).mean()


# --- the voxels -----------------------------------------------------------------------------------------------------

def free_prior_loss(density: torch.Tensor) -> torch.Tensor:
    """Unweighted free prior: mean over all voxels of -log(1 - σ), density [B, X, Y, Z] in [0, 1] (clamped at
    1 - 1e-4): it charges every voxel by how much light it would stop; the rays' terms outweigh it where rays go.
    The same -log(1 - x) as ``free_space_loss``,
    over voxels instead of beams."""
    with torch.autocast(device_type=density.device.type, enabled=False):
        return free_space_loss(density.float().reshape(-1))


def voxel_targets(semantics_gt: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """What the 3D terms supervise in one sample, as rows of its flattened grid [X·Y·Z] (row = (x·Y + y)·Z + z,
    grid layout, ego frame): semantics_gt uint8/long [X, Y, Z] (17 = free); mask bool [X, Y, Z] (``mask_camera``,
    with ``voxel_mask``) or None (every voxel, as the official 3D training) →

    - "voxel_rows" int64 [K]: the kept voxels (only with a mask; without one every voxel is kept, in row order);
    - "voxel_occupied" float32 [K] (or [X·Y·Z]): the density BCE's targets, 1 where the label is occupied;
    - "voxel_classes" uint8 [K] (or [X·Y·Z]): the kept voxels' labels (17 = free), for the affinity terms;
    - "occupied_rows" int64 [K'], "occupied_labels" int64 [K']: the kept occupied voxels and their classes.

    The data loader adds them to each 3D sample (``occflownet.train.dataset``; ``collate`` offsets the rows by the
    sample's place in the batch), so the model's heads can run on those rows only
    (``OccupancyModel.forward(density_at=, logits_at=)``)."""
    if semantics_gt.dim() != 3:
        raise ValueError(f"semantics_gt must be [X, Y, Z], got {tuple(semantics_gt.shape)}")
    labels = semantics_gt.reshape(-1)          # as given (uint8 from the loader): 8 times less to read than int64
    low, high = torch.aminmax(labels)
    if int(low) < 0 or int(high) > FREE:
        raise ValueError(f"semantics_gt values must lie in [0, {FREE}]")
    occupied = labels != FREE
    out = {}
    if mask is not None:
        if mask.shape != semantics_gt.shape:
            raise ValueError(f"mask must be {tuple(semantics_gt.shape)}, got {tuple(mask.shape)}")
        keep = mask.bool().reshape(-1)
        out["voxel_rows"] = torch.nonzero(keep).reshape(-1)
        out["voxel_occupied"] = occupied[keep].float()
        out["voxel_classes"] = labels[keep]
        occupied = occupied & keep
    else:
        out["voxel_occupied"] = occupied.float()
        out["voxel_classes"] = labels
    out["occupied_rows"] = torch.nonzero(occupied).reshape(-1)
    out["occupied_labels"] = labels[out["occupied_rows"]].long()
    return out


def voxel_density_loss(sigma: torch.Tensor, occupied: torch.Tensor) -> torch.Tensor:
    """BCE(σ, occupied), mean over the supervised voxels: sigma [K] in [0, 1] (the density at the rows of
    :func:`voxel_targets`), occupied float [K] (its "voxel_occupied"). K = 0 gives 0 (graph kept)."""
    if sigma.shape != occupied.shape or sigma.dim() != 1:
        raise ValueError(f"sigma and occupied must both be [K], got {tuple(sigma.shape)} and {tuple(occupied.shape)}")
    if not sigma.numel():
        return sigma.sum() * 0
    with torch.autocast(device_type=sigma.device.type, enabled=False):
        return F.binary_cross_entropy(sigma.float(), occupied.float())


def voxel_semantics_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """CE of the logits [K', 17] of the supervised occupied voxels against their classes labels [K'] (long),
    mean, unweighted. K' = 0 gives 0 (graph kept)."""
    if logits.dim() != 2 or logits.shape[-1] != NUM_CLASSES or labels.shape != logits.shape[:1]:
        raise ValueError(f"logits must be [K, {NUM_CLASSES}] and labels [K], got {tuple(logits.shape)} and "
                         f"{tuple(labels.shape)}")
    if logits.shape[0] == 0:
        return logits.sum() * 0.0
    return F.cross_entropy(logits, labels.long())


def _affinity(p: torch.Tensor, y: torch.Tensor, eps: float = 1e-6) -> tuple[torch.Tensor, int]:
    """Σ over columns of -log precision - log recall - log specificity of the soft predictions p [K, C] in [0, 1]
    against the 0/1 targets y [K, C], each column a class; a column's term whose denominator is 0 (no prediction,
    no positive, no negative) is left out, and a column without a positive is left out whole. Returns
    (the sum over the kept columns, their count)."""
    tp, predicted, positive = (p * y).sum(0), p.sum(0), y.sum(0)
    negative = y.shape[0] - positive
    true_negative = negative - predicted + tp                     # Σ (1 - p)(1 - y)
    kept = positive > 0
    terms = [(tp / predicted.clamp_min(eps), kept & (predicted.detach() > 0)), (tp / positive.clamp_min(eps), kept),
             (true_negative / negative.clamp_min(eps), kept & (negative > 0))]
    total = sum(-torch.log(ratio.clamp_min(eps))[on].sum() for ratio, on in terms)
    return total, int(kept.sum())


def voxel_scal_loss(sigma: torch.Tensor, logits: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
    """Scene-class affinity (MonoScene's geo_scal + sem_scal) over the supervised voxels: sigma [K] in [0, 1],
    logits [K, 17] and classes [K] (17 = free) at the rows of :func:`voxel_targets`. Occupancy p = σ against
    label != 17, and per class c present in ``classes`` p_c = σ·softmax(logits)_c against label == c; the occupancy
    term plus the mean of the class terms. K = 0 gives 0 (graph kept)."""
    if sigma.dim() != 1 or logits.shape != (sigma.shape[0], NUM_CLASSES) or classes.shape != sigma.shape:
        raise ValueError(f"sigma [K], logits [K, {NUM_CLASSES}], classes [K] expected, got {tuple(sigma.shape)}, "
                         f"{tuple(logits.shape)}, {tuple(classes.shape)}")
    if not sigma.numel():
        return sigma.sum() * 0 + logits.sum() * 0
    with torch.autocast(device_type=sigma.device.type, enabled=False):
        sigma, logits, classes = sigma.float(), logits.float(), classes.long()
        onehot = F.one_hot(classes, FREE + 1)[:, :FREE].float()             # [K, 17]; free voxels all zero
        geo, _ = _affinity(sigma[:, None], onehot.sum(1, keepdim=True))
        sem, present = _affinity(sigma[:, None] * torch.softmax(logits, dim=-1), onehot)
        return geo + sem / max(present, 1)


# --- the LiDAR depth of the LSS depth distribution, the class of each feature cell ---------------------------------
def nearest_points(feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor, points_ego: Sequence[torch.Tensor],
                   feature_size: tuple[int, int], labels: Sequence[torch.Tensor] | None = None):
    """The nearest LiDAR point in each feature pixel → (depth float64 [B·N·h·w]: its camera z-depth, inf where no
    point lands; label int64 [B·N·h·w]: its label, -1 where none (ties at equal depth: the smallest label), or None
    without ``labels``). Pixels are ordered [B, N, h, w].

    feature_intrinsics [B, N, 3, 3]: camera frame (OpenCV) → feature-map pixels, pixel centres at integer
    coordinates (for stride s: fx/s, fy/s, (cx + 0.5)/s - 0.5, (cy + 0.5)/s - 0.5); a point lands in feature
    pixel (round(u), round(v)) when it lies in front of the camera. cam2ego [B, N, 4, 4]. points_ego: B tensors
    [N_b, 3], LiDAR points of the current frame in the ego frame; labels: B tensors [N_b] (integers), their classes.
    """
    b, n_cam = feature_intrinsics.shape[:2]
    h, w = feature_size
    if cam2ego.shape != (b, n_cam, 4, 4) or feature_intrinsics.shape != (b, n_cam, 3, 3):
        raise ValueError(f"feature_intrinsics must be [B, N, 3, 3] and cam2ego [B, N, 4, 4], got "
                         f"{tuple(feature_intrinsics.shape)} and {tuple(cam2ego.shape)}")
    if len(points_ego) != b or (labels is not None and len(labels) != b):
        raise ValueError(f"points_ego (and labels) must hold {b} tensors (one per batch item), got {len(points_ego)}")
    device = feature_intrinsics.device
    nearest = torch.full((b * n_cam * h * w,), float("inf"), dtype=torch.float64, device=device)
    hits = []                                                      # (flat pixel, depth, label) of every landed point
    ego2cam = torch.linalg.inv(cam2ego.to(torch.float64))
    k = feature_intrinsics.to(torch.float64)
    for bi, pts in enumerate(points_ego):
        if pts.dim() != 2 or pts.shape[1] < 3 or (labels is not None and labels[bi].shape != pts.shape[:1]):
            raise ValueError(f"points_ego[{bi}] must be [N, 3] (and labels[{bi}] [N]), got {tuple(pts.shape)}")
        p = pts[:, :3].to(device=device, dtype=torch.float64)
        for ci in range(n_cam):
            cam = p @ ego2cam[bi, ci, :3, :3].T + ego2cam[bi, ci, :3, 3]
            front = cam[:, 2] > 1e-6
            uvw = cam[front] @ k[bi, ci].T
            col = torch.round(uvw[:, 0] / uvw[:, 2])
            row = torch.round(uvw[:, 1] / uvw[:, 2])
            ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
            flat = ((bi * n_cam + ci) * h + row[ok].long()) * w + col[ok].long()
            z = cam[front, 2][ok]
            nearest.scatter_reduce_(0, flat, z, reduce="amin")
            if labels is not None:
                hits.append((flat, z, labels[bi].to(device)[front][ok].long()))
    if labels is None:
        return nearest, None
    label = torch.full_like(nearest, NUM_CLASSES + 1, dtype=torch.int64)
    for flat, z, lab in hits:
        won = z == nearest[flat]
        label.scatter_reduce_(0, flat[won], lab[won], reduce="amin")
    return nearest, torch.where(torch.isinf(nearest), torch.full_like(label, -1), label)


def lidar_depth_targets(feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                        points_ego: Sequence[torch.Tensor], feature_size: tuple[int, int],
                        depth_bin_centers: torch.Tensor) -> torch.Tensor:
    """Depth-bin targets of the feature maps → long [B, N_cam, h, w]: bin index, or -1 where no point lands.

    Inputs as :func:`nearest_points`. The depth is the camera z-depth (the LSS frustum's depth); the target of a
    pixel is the bin whose centre is nearest to the smallest depth among its points; depths more than half a
    bin outside [centers[0], centers[-1]] give no target.
    """
    centers = depth_bin_centers.to(torch.float64)
    if centers.dim() != 1 or centers.numel() < 2 or not bool((centers[1:] > centers[:-1]).all()):
        raise ValueError("depth_bin_centers must be an increasing 1-D tensor with at least 2 bins")
    nearest, _ = nearest_points(feature_intrinsics, cam2ego, points_ego, feature_size)
    centers = centers.to(nearest.device)
    half_lo = 0.5 * (centers[1] - centers[0])
    half_hi = 0.5 * (centers[-1] - centers[-2])
    valid = (nearest >= centers[0] - half_lo) & (nearest <= centers[-1] + half_hi)
    boundaries = 0.5 * (centers[1:] + centers[:-1])
    bins = torch.bucketize(nearest.clamp(max=float(centers[-1]) + 1.0), boundaries)
    return torch.where(valid, bins, torch.full_like(bins, -1)).view(*feature_intrinsics.shape[:2], *feature_size)


def lidar_depth_loss(depth_prob: torch.Tensor, feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                     points_ego: Sequence[torch.Tensor], depth_bin_centers: torch.Tensor) -> torch.Tensor:
    """BCE between the LSS depth distribution depth_prob [B, N, D, h, w] (probabilities over D) and one-hot
    LiDAR targets (``lidar_depth_targets``): summed over the D bins, averaged over pixels with a target
    (0 when no pixel has one). Unweighted (the "lidar_depth" term weighs it by ``lidar_depth_weight``)."""
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


def image_semantics_loss(image_logits: torch.Tensor, feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                         points_ego: Sequence[torch.Tensor], point_labels: Sequence[torch.Tensor]) -> torch.Tensor:
    """Cross-entropy of the image head's logits [B, N, 17, h, w] against the label of the nearest LiDAR point in
    each feature pixel (:func:`nearest_points`), averaged over the pixels a point lands in (0 when none does).
    Unweighted (the "image_semantics" term weighs it by ``image_semantics_weight``)."""
    if image_logits.dim() != 5 or image_logits.shape[2] != NUM_CLASSES:
        raise ValueError(f"image_logits must be [B, N, {NUM_CLASSES}, h, w], got {tuple(image_logits.shape)}")
    with torch.no_grad():
        _, target = nearest_points(feature_intrinsics, cam2ego, points_ego, tuple(image_logits.shape[-2:]),
                                   point_labels)
    has_target = target >= 0
    if not bool(has_target.any()):
        return image_logits.sum() * 0.0
    logits = image_logits.permute(0, 1, 3, 4, 2).reshape(-1, NUM_CLASSES)
    return F.cross_entropy(logits[has_target].float(), target[has_target])
