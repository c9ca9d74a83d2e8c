import copy

import pytest
import torch

from occflownet.occ3d import FREE, NUM_CLASSES
from occflownet.model import create_model, fuse_occupancy, get_preset
from occflownet.model.preprocess import preprocess_images, scale_intrinsics_to_features
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig


def _inputs(batch=1, width=160, height=90, seed=0):
    K, T = calibration_arrays(default_rig(width, height))
    g = torch.Generator().manual_seed(seed)
    images = torch.randint(0, 256, (batch, 6, height, width, 3), dtype=torch.uint8, generator=g)
    return images, torch.from_numpy(K)[None].repeat(batch, 1, 1, 1), torch.from_numpy(T)[None].repeat(batch, 1, 1, 1)


@pytest.fixture(scope="module")
def tiny():
    """Random-init tiny with Φσ's bias shifted so that σ straddles τ (about half the voxels occupied) and Φs's
    output bias zeroed so that the argmax varies."""
    model = create_model(get_preset("tiny"), seed=0).eval()
    with torch.no_grad():
        median = torch.logit(model.inference(*_inputs())[1]).median()
        model.decoder.sigma_head[-1].bias += torch.logit(torch.tensor(0.35)) - median
        model.decoder.semantic_head[-1].bias.zero_()
    return model


def test_forward_outputs_follow_the_contract(tiny):
    cfg = tiny.cfg
    images, K, T = _inputs(batch=2)
    with torch.no_grad():
        out = tiny(images, K, T)
    h, w = cfg.feature_size
    assert out["density"].shape == (2, 200, 200, 16) and out["density"].dtype == torch.float32
    assert out["logits"].shape == (2, 200, 200, 16, NUM_CLASSES)
    assert out["depth_prob"].shape == (2, 6, cfg.num_depth_bins, h, w)
    assert out["feature_intrinsics"].shape == (2, 6, 3, 3)
    assert out["occupancy"].shape == (2, 200, 200, 16) and out["occupancy"].dtype == torch.uint8
    d = out["density"]
    assert 0.0 <= d.min() and d.max() <= 1.0
    assert torch.allclose(out["depth_prob"].sum(2), torch.ones(2, 6, h, w), atol=1e-5)
    expected_k = scale_intrinsics_to_features(
        preprocess_images(images, K, cfg.input_size, cfg.image_mean, cfg.image_std)[1], 16)
    # exact: forward runs these same two functions on the same tensors (same ops, same order)
    assert torch.equal(out["feature_intrinsics"], expected_k)
    assert torch.equal(out["occupancy"], fuse_occupancy(d, out["logits"], cfg.threshold))
    occ, dens = tiny.inference(images, K, T)                  # Φs only where σ ≥ τ: same fused result
    # inference sums the pooling in another order (sorted segment sums) and runs the trunk as 2-D convolutions:
    # the same map up to float32 rounding
    assert torch.allclose(dens, d, atol=1e-5, rtol=0)
    # Φs runs on the occupied rows only in inference, on every row in forward: a matrix product over other row
    # counts may round differently on other CPUs (~1e-6 of the logits), which can flip the argmax of a voxel whose
    # two best classes are that close, or whose σ lies within rounding of τ; every other voxel has the same class.
    away = (d - cfg.threshold).abs() > 1e-5
    differ = (occ != out["occupancy"]) & away
    top2 = out["logits"].topk(2, dim=-1).values
    assert float(differ.float().mean()) < 1e-4 and float(away.float().mean()) > 0.99
    assert bool((top2[..., 0] - top2[..., 1])[differ].le(1e-4).all()) and torch.equal(occ == FREE, dens < cfg.threshold)
    assert 0.2 < (occ != FREE).float().mean() < 0.8 and len(occ.unique()) >= 3


def test_fusion_rule():
    density = torch.tensor([0.2, 0.35, 0.9])
    logits = torch.zeros(3, NUM_CLASSES)
    logits[:, 4] = 1.0
    assert fuse_occupancy(density, logits, 0.35).tolist() == [FREE, 4, 4]


def test_backward_reaches_every_parameter():
    model = create_model(get_preset("tiny"), seed=0).train()
    images, K, T = _inputs()
    out = model(images, K, T)
    loss = out["density"].mean() + out["logits"].square().mean() + (out["depth_prob"] + 1e-6).log().mean()
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert sum(float(p.grad.abs().sum()) for p in model.parameters()) > 0


def test_the_image_head_is_trained_only_and_leaves_the_rest_as_it_was():
    """ModelConfig.image_semantics adds a head giving each feature cell's class [B, 6, 17, h, w]; it is created
    after every other module, so the other weights are those of the model without it, and neither forward's other
    outputs nor inference() change."""
    plain = create_model(get_preset("tiny"), seed=0).train()
    headed = create_model(get_preset("tiny", image_semantics=True), seed=0).train()
    shared = plain.state_dict()
    assert all(torch.equal(v, shared[k]) for k, v in headed.state_dict().items() if not k.startswith("image_head"))
    assert "image_logits" not in plain(*_inputs())
    out = headed(*_inputs())
    h, w = headed.cfg.feature_size
    assert out["image_logits"].shape == (1, 6, NUM_CLASSES, h, w)
    out["image_logits"].square().mean().backward()
    assert headed.image_head.weight.grad.abs().sum() > 0 and headed.backbone.conv1.weight.grad.abs().sum() > 0
    with torch.no_grad():
        # exact: the same weights and the same ops in the same order (the head only reads the features)
        assert all(torch.equal(a, b) for a, b in zip(plain.eval().inference(*_inputs()),
                                                     headed.eval().inference(*_inputs())))


def test_training_forward_runs_under_bf16_autocast_and_agrees_with_float32():
    """--amp on a bf16 device: the network under torch.autocast(bfloat16) (the decoder's scatter-add stays float32)
    trains, every gradient finite, and its outputs follow the float32 ones (bf16 keeps ~3 significant digits)."""
    model = create_model(get_preset("tiny"), seed=0).train()
    images, K, T = _inputs()
    ref = model(images, K, T)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(images, K, T)
    density, logits = out["density"].float(), out["logits"].float()
    (density.mean() + logits.square().mean()).backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    for a, b in ((density, ref["density"]), (logits, ref["logits"])):
        a, b = a.detach().flatten(), b.detach().flatten()
        assert torch.corrcoef(torch.stack([a, b]))[0, 1] > 0.99
        assert float((a - b).abs().max()) < 0.1 * float(b.abs().max())


def test_same_seed_same_weights():
    a = create_model(get_preset("tiny"), seed=7).state_dict()
    b = create_model(get_preset("tiny"), seed=7).state_dict()
    c = create_model(get_preset("tiny"), seed=8).state_dict()
    # exact: the same initialisation run twice from the same seed (same ops, same order)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_calibration_changes_the_prediction(tiny):
    images, K, T = _inputs()
    T2 = T.clone()
    T2[..., 0, 3] += 3.0                                      # move the rig 3 m forward
    with torch.no_grad():
        d1 = tiny.inference(images, K, T)[1]
        d2 = tiny.inference(images, K, T2)[1]
    assert (d1 - d2).abs().max() > 1e-3


def test_block_rows_is_the_inverse_of_unblock():
    """block_rows maps a grid-layout row to the row unblock reads it from, for every stride and batch element."""
    from occflownet.model.decoder import block_rows, unblock

    shape = (8, 12, 4)
    for stride in (1, 2, 4):
        b = 2
        block = torch.arange(b * 8 * 12 * 4).reshape(b, 8 // stride, 12 // stride, 4 // stride, stride ** 3)
        grid = unblock(block, stride).reshape(-1)                 # grid row r holds the block row it came from
        rows = torch.randperm(grid.numel(), generator=torch.Generator().manual_seed(stride))
        assert torch.equal(block_rows(rows, shape, stride), grid[rows])


def test_heads_at_rows_equal_the_full_grid_at_those_rows(tiny):
    """forward(density_at=, logits_at=) runs the heads on the asked voxels only and gives exactly the full
    forward's values there (in the rows' order), in eval and in training mode, for a batch of two."""
    images, K, T = _inputs(batch=2)
    g = torch.Generator().manual_seed(1)
    rows_d = torch.randint(0, 2 * 200 * 200 * 16, (5000,), generator=g)
    rows_l = torch.randint(0, 2 * 200 * 200 * 16, (3000,), generator=g)
    for train in (False, True):
        model = copy.deepcopy(tiny).train(train)            # training mode updates BatchNorm statistics
        with torch.no_grad():
            torch.manual_seed(0)
            full = model(images, K, T)
            torch.manual_seed(0)
            part = model(images, K, T, density_at=rows_d, logits_at=rows_l)
        assert part["density"].shape == (5000,) and part["logits"].shape == (3000, NUM_CLASSES)
        assert "occupancy" not in part and ("occupancy" in full) == (not train)
        torch.testing.assert_close(part["density"], full["density"].reshape(-1)[rows_d], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(part["logits"], full["logits"].reshape(-1, NUM_CLASSES)[rows_l],
                                   rtol=1e-6, atol=1e-6)
        only_d = model(images, K, T, density_at=rows_d)      # one head restricted, the other over the grid
        assert only_d["logits"].shape == (2, 200, 200, 16, NUM_CLASSES)


@pytest.mark.parametrize("rows", [640_000, 1_000, 37])
def test_voxel_mlp_trains_with_the_gradients_of_its_modules(rows):
    """VoxelMLP (the heads) in training runs its Linear layers as RowLinear, whose backward sums the weight gradient
    over row blocks (and a one-output layer's input gradient as a broadcast product): the same outputs, and the same
    gradients up to the order of summation, as the plain modules, for row counts that fill the blocks or not; in eval
    and under autocast it is the modules themselves."""
    from occflownet.model.decoder import mlp

    torch.manual_seed(0)
    for out in (1, 17):
        head = mlp(8, (16,), out)
        x = torch.randn(rows, 8)
        results = []
        for rowwise in (True, False):
            head.zero_grad()
            xi = x.clone().requires_grad_(True)
            head.train()
            y = head(xi) if rowwise else torch.nn.Sequential.forward(head, xi)
            assert ("RowLinear" in type(y.grad_fn).__name__) == rowwise
            (y.square().sum() / rows).backward()
            results.append([y.detach(), xi.grad] + [p.grad.clone() for p in head.parameters()])
        for a, b in zip(*results):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert "RowLinear" not in type(head(x.requires_grad_(True)).grad_fn).__name__
    head.eval()
    with torch.no_grad():        # exact: in eval VoxelMLP.forward is Sequential.forward (the same modules run)
        assert torch.equal(head(x), torch.nn.Sequential.forward(head, x))


def test_decoder_features_while_training_equal_the_out_of_place_ops():
    """voxel_features sums the fine points into the upsampled rows and rectifies them in one buffer while training
    (FineRows: no copy of every row, forward or backward); the values and every gradient are bitwise those of the
    out-of-place ops that eval runs, up to float32 rounding: FineRows's products and sums are those autograd runs,
    but a CPU's kernels may order a product's sums differently for the transposed layouts (3.8e-6 on gradients of
    magnitude ~30 on an AVX-512 AMD CPU, 0 on others)."""
    from occflownet.model.decoder import VoxelDecoder

    torch.manual_seed(0)
    decoder = VoxelDecoder(in_channels=6, stride=2, channels=8, blocks=1, head_channels=4, sigma_hidden=(16,),
                           semantic_hidden=(8,))
    trunk = torch.randn(1, 5, 5, 2, 6)
    rows = torch.tensor([0, 3, 3, 199, 57])               # repeated rows add up
    values = torch.randn(5, 4)

    def run(fused: bool):
        decoder.zero_grad()
        decoder.train()
        src = values.clone().requires_grad_(True)
        if fused:
            x = decoder.voxel_features(trunk, (rows, src))
        else:                                             # the ops eval runs, on the training-mode trunk
            up = decoder.up(decoder.trunk_rows(trunk)).reshape(-1, decoder.head_channels)
            x = torch.relu(torch.index_add(up, 0, rows, src))
        (x * torch.linspace(-1, 1, x.numel()).reshape(x.shape)).sum().backward()
        return [x.detach(), src.grad] + [p.grad.clone() for p in decoder.parameters() if p.grad is not None]

    fused, out_of_place = run(True), run(False)
    assert len(fused) == len(out_of_place) > 3
    for a, b in zip(fused, out_of_place):
        # float32 rounding: eps 1.2e-7 per operation, sums of at most M·s³ = 400 terms, cancellation inside a
        # tensor, so relative to the tensor's largest value; a wrong op (mask, row, transpose) is off by O(1)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
