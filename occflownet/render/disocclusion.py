"""Disocclusion for temporal frames: remove predicted dynamic objects from the density (paper section 3.5).

In frames t ≠ 0 the official code renders a copy of the volume in which every voxel whose *predicted* class
(argmax of the logits) is dynamic has σ = 0, so that background revealed by a moving object is rendered with
its static label. Only the density changes; the logits stay, and gradients flow to σ of the other voxels.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch

from occflownet.occ3d import DYNAMIC_FILTER_CLASSES


def dynamic_mask(logits: torch.Tensor, classes: Sequence[int] = DYNAMIC_FILTER_CLASSES) -> torch.Tensor:
    """Bool [..., X, Y, Z]: argmax of logits [..., X, Y, Z, C] is one of ``classes``."""
    if logits.dim() < 1 or logits.shape[-1] < 1:
        raise ValueError(f"logits must have a trailing class dimension, got {tuple(logits.shape)}")
    bad = [c for c in classes if not 0 <= int(c) < logits.shape[-1]]
    if bad:
        raise ValueError(f"classes {bad} are outside the {logits.shape[-1]} logit channels")
    predicted = logits.argmax(dim=-1)
    lut = torch.zeros(logits.shape[-1], dtype=torch.bool, device=logits.device)
    if len(classes):
        lut[torch.as_tensor(list(classes), dtype=torch.long, device=logits.device)] = True
    return lut[predicted]


def disocclude(density: torch.Tensor, logits: torch.Tensor,
               classes: Sequence[int] = DYNAMIC_FILTER_CLASSES, rows: torch.Tensor | None = None) -> torch.Tensor:
    """A copy of density [..., X, Y, Z] with σ = 0 where argmax(logits [..., X, Y, Z, C]) ∈ ``classes``; with
    ``rows`` (long [K]) the logits are [K, C] at those rows of the flattened density (the other voxels keep σ).

    Differentiable with respect to the density of the voxels that are kept; the input is not modified.
    """
    if rows is not None:
        if logits.dim() != 2 or rows.shape != logits.shape[:1]:
            raise ValueError(f"logits at rows must be [K, C] for rows [K], got {tuple(logits.shape)} and "
                             f"{tuple(rows.shape)}")
        mask = torch.zeros(density.numel(), dtype=torch.bool, device=density.device)
        mask = mask.index_copy(0, rows, dynamic_mask(logits.detach(), classes)).reshape(density.shape)
    elif tuple(logits.shape[:-1]) != tuple(density.shape):
        raise ValueError(f"density {tuple(density.shape)} and logits {tuple(logits.shape)} disagree: logits must "
                         "be density's shape plus a class dimension")
    else:
        mask = dynamic_mask(logits.detach(), classes)
    return torch.where(mask, torch.zeros_like(density), density)
