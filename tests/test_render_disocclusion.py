"""Disocclusion (occflownet.render.disocclusion): σ = 0 exactly where the predicted class is dynamic."""
from __future__ import annotations

import pytest
import torch

from occflownet.occ3d import DYNAMIC_FILTER_CLASSES, NUM_CLASSES
from occflownet.render.disocclusion import disocclude, dynamic_mask


def test_zeroes_exactly_the_dynamic_voxels_and_keeps_gradients_elsewhere():
    gen = torch.Generator().manual_seed(0)
    density = torch.rand(2, 6, 5, 4, generator=gen).requires_grad_(True)
    labels = torch.randint(0, NUM_CLASSES, (2, 6, 5, 4), generator=gen)
    logits = torch.nn.functional.one_hot(labels, NUM_CLASSES).float() * 3 + 0.1 * torch.randn(
        2, 6, 5, 4, NUM_CLASSES, generator=gen)
    expected = torch.isin(labels, torch.tensor(DYNAMIC_FILTER_CLASSES))
    assert 0 < int(expected.sum()) < expected.numel()
    out = disocclude(density, logits)
    # exact: disocclusion multiplies by 0 or 1 (a mask), which rounds nothing
    assert torch.equal(dynamic_mask(logits), expected)
    assert torch.all(out[expected] == 0)
    assert torch.equal(out[~expected], density[~expected])
    out.sum().backward()
    assert torch.equal(density.grad, (~expected).float())
    assert density.detach().min() > 0  # input untouched


def test_custom_classes_and_no_classes():
    logits = torch.zeros(1, 2, 2, 2, NUM_CLASSES)
    logits[0, 0, 0, 0, 11] = 1.0  # driveable surface: static
    logits[0, 1, 1, 1, 4] = 1.0   # car
    density = torch.ones(1, 2, 2, 2)
    assert disocclude(density, logits, classes=(11,))[0, 0, 0, 0] == 0
    assert torch.equal(disocclude(density, logits, classes=()), density)
    assert disocclude(density, logits)[0, 1, 1, 1] == 0  # car is in the official filter set


def test_rejects_mismatched_shapes_and_bad_classes():
    with pytest.raises(ValueError, match="disagree"):
        disocclude(torch.ones(1, 2, 2, 2), torch.zeros(1, 2, 2, 3, NUM_CLASSES))
    with pytest.raises(ValueError, match="outside"):
        disocclude(torch.ones(1, 2, 2, 2), torch.zeros(1, 2, 2, 2, NUM_CLASSES), classes=(17,))
