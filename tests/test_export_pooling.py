"""The voxel pooling stage exported alone: the exported path's sorted segment sums, the scatter-add rewrite that the
export applies to any ``index_add``, and the 90° rig-rotation geometry.

Eval mode (the exported model) pools by sorted segment sums: no scatter with a reduction, the same sums as
``index_add`` to float32 rounding, the same bits on every run. The training path's ``index_add`` exports as
``ScatterND(reduction="add")``, which onnxruntime runs on several threads without synchronisation (lost updates at
random); the export rewrites any such node as ScatterElements (``deterministic_scatter_add``), whose sums are
bit-identical to torch's ``index_add`` on every run; the TorchScript exporter's known bug (index_add → ScatterND
*without* reduction) keeps only one of the repeated updates per voxel, which
``test_the_repeated_index_check_catches_a_scatter_without_reduction`` shows the checks would catch.
"""
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from occflownet.export.onnx_export import ExportError, deterministic_scatter_add, trace_to_onnx
from occflownet.model.lift import LiftSplat
from test_model_lift import _rig, assert_rotated, fine_grid

H, W = 6, 10


class PoolingStage(torch.nn.Module):
    """depth_prob [1, 6, D, h, w], context [1, 6, h, w, C], intrinsics, cam2ego → (trunk grid, dense fine grid),
    pooled by the training path's ``index_add`` (``scatter_add=True``) or the eval path's sorted segment sums."""

    def __init__(self, depths, stride, scatter_add: bool):
        super().__init__()
        self.lift = LiftSplat(depths, stride)
        self.scatter_add = scatter_add

    def forward(self, depth_prob, context, feature_intrinsics, cam2ego):
        self.lift.training = self.scatter_add
        trunk, fine_points = self.lift(depth_prob, context, context, feature_intrinsics, cam2ego)
        if self.scatter_add:
            return trunk, fine_grid(fine_points, depth_prob.shape[0], self.lift.stride)
        return trunk, fine_points[0], fine_points[1]


def _inputs(depths, seed=0):
    K, T = _rig(H, W)
    T[..., :3, 3] += torch.tensor([0.013, 0.007, 0.0])       # no frustum point exactly on a voxel face
    g = torch.Generator().manual_seed(seed)
    depth_prob = torch.softmax(2 * torch.randn(1, 6, len(depths), H, W, generator=g), 2)
    context = torch.rand(1, 6, H, W, 3, generator=g)
    return depth_prob, context, K, T


# depth bins 1 cm apart: every pixel's 16 frustum points share a voxel, neighbouring pixels often too
DEPTHS = [6.0 + 0.01 * i for i in range(16)]
NAMES = ["depth_prob", "context", "feature_intrinsics", "cam2ego"]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The training path's index_add pooling, exported and rewritten as the export does."""
    module = PoolingStage(DEPTHS, stride=2, scatter_add=True).eval()
    path = tmp_path_factory.mktemp("pool") / "pool.onnx"
    traced = trace_to_onnx(module, _inputs(DEPTHS), path, NAMES, ["trunk", "fine"], None)
    proto = onnx.ModelProto()
    proto.CopyFrom(traced)
    assert deterministic_scatter_add(proto) == 2                  # trunk and fine pooling
    return module, DEPTHS, proto, traced


@pytest.fixture(scope="module")
def exported_sorted(tmp_path_factory):
    """The eval path's sorted segment sums, exported (the rewrite finds nothing to do)."""
    module = PoolingStage(DEPTHS, stride=2, scatter_add=False).eval()
    path = tmp_path_factory.mktemp("pool") / "pool_sorted.onnx"
    proto = trace_to_onnx(module, _inputs(DEPTHS), path, NAMES, ["trunk", "rows", "sums"], None)
    assert deterministic_scatter_add(proto) == 0
    return module, proto


def _run(proto, inputs, threads=0):
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    session = ort.InferenceSession(proto.SerializeToString(), so, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    return session.run(None, {n: t.numpy() for n, t in zip(names, inputs)})


def test_pooling_with_many_points_per_voxel(exported):
    module, depths, proto, _ = exported
    inputs = _inputs(depths, seed=1)
    rows = module.lift(inputs[0], inputs[1], None, inputs[2], inputs[3])[0]
    occupied = (rows.abs().sum(-1) > 0).sum().item()
    assert 6 * H * W * len(depths) > 10 * occupied            # heavy repetition: > 10 points per used voxel
    with torch.no_grad():
        trunk_t, fine_t = module(*inputs)
    trunk_o, fine_o = _run(proto, inputs)
    assert np.allclose(trunk_o, trunk_t.numpy(), atol=1e-5) and np.allclose(fine_o, fine_t.numpy(), atol=1e-5)
    assert trunk_o.sum() == pytest.approx(float(trunk_t.sum()), rel=1e-5)


def test_rewritten_pooling_is_bit_identical_to_torch_on_every_run(exported):
    """ScatterElements adds in index order like torch's index_add: the same bits on every run, at 4 threads too."""
    module, depths, proto, _ = exported
    assert {n.op_type for n in proto.graph.node if n.op_type.startswith("Scatter")} == {"ScatterElements"}
    ranks = {v.name: len(v.type.tensor_type.shape.dim)
             for v in onnx.shape_inference.infer_shapes(proto).graph.value_info}
    scatters = [n for n in proto.graph.node if n.op_type == "ScatterElements"]
    assert [ranks[n.input[0]] for n in scatters] == [1, 1]        # the 1-D form (flattened data and updates)
    inputs = _inputs(depths, seed=3)
    with torch.no_grad():
        trunk_t, fine_t = module(*inputs)
    # exact by construction: frustum_points uses elementwise products and sums only (no MatMul), so both runtimes
    # compute the same coordinates and voxel indices; the products are elementwise; and the sums run in index order
    for _ in range(5):
        trunk_o, fine_o = _run(proto, inputs, threads=4)
        assert np.array_equal(trunk_o, trunk_t.numpy()) and np.array_equal(fine_o, fine_t.numpy())


def test_rewrite_refuses_a_scatter_it_does_not_understand(exported):
    _, _, _, traced = exported
    odd = onnx.ModelProto()
    odd.CopyFrom(traced)
    node = next(n for n in odd.graph.node if n.op_type == "ScatterND")
    node.input[1] = node.input[2]                                  # float [N, C] "indices": not [N, 1]
    with pytest.raises(ExportError, match="2-D pooling form"):
        deterministic_scatter_add(odd)


def test_the_repeated_index_check_catches_a_scatter_without_reduction(exported):
    """Sanity check of the test above: the same graph with ScatterND's reduction removed loses updates."""
    module, depths, _, traced = exported
    broken = onnx.ModelProto()
    broken.CopyFrom(traced)
    scatters = [n for n in broken.graph.node if n.op_type == "ScatterND"]
    assert scatters
    for node in scatters:
        assert [a.s for a in node.attribute if a.name == "reduction"] == [b"add"]
        kept = [a for a in node.attribute if a.name != "reduction"]
        del node.attribute[:]
        node.attribute.extend(kept)
    inputs = _inputs(depths, seed=1)
    with torch.no_grad():
        trunk_t, _ = module(*inputs)
    trunk_o, _ = _run(broken, inputs)
    assert not np.allclose(trunk_o, trunk_t.numpy(), atol=1e-3)


def test_turning_the_rig_turns_the_exported_pooling(exported_sorted):
    module, proto = exported_sorted
    depth_prob, context, K, T = _inputs(DEPTHS, seed=2)
    turn = torch.eye(4)
    turn[:2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])

    def dense(rows, sums):
        return fine_grid((torch.as_tensor(rows), torch.as_tensor(sums)), 1, 2)

    fine = dense(*_run(proto, (depth_prob, context, K, T))[1:])
    fine_turned = dense(*_run(proto, (depth_prob, context, K, turn @ T))[1:])
    assert_rotated(fine, fine_turned)
    with torch.no_grad():
        assert torch.allclose(dense(*module(depth_prob, context, K, turn @ T)[1:]), fine_turned, atol=1e-5)


def test_exported_sorted_pooling_equals_the_index_add_sums(exported_sorted):
    module, proto = exported_sorted
    assert {(n.op_type, next((a.s.decode() for a in n.attribute if a.name == "reduction"), "none"))
            for n in proto.graph.node if n.op_type.startswith("Scatter")} == {("ScatterND", "none")}
    inputs = _inputs(DEPTHS, seed=1)
    reference = PoolingStage(DEPTHS, stride=2, scatter_add=True)
    with torch.no_grad():
        trunk_i, fine_i = reference(*inputs)                       # index_add, in point order
        trunk_t, rows_t, sums_t = module(*inputs)
    trunk_o, rows_o, sums_o = _run(proto, inputs)
    points = 6 * H * W * len(DEPTHS)                               # heavy repetition: many points per used voxel
    assert points > 10 * (np.abs(trunk_o).sum(-1) > 0).sum() and points > 5 * len(rows_o)
    assert np.array_equal(rows_o, rows_t.numpy())                  # exact: integer voxel rows
    assert np.allclose(trunk_o, trunk_t.numpy(), rtol=1e-6, atol=1e-6)
    assert np.allclose(sums_o, sums_t.numpy(), rtol=1e-6, atol=1e-6)
    # the same sums as index_add up to float32 rounding of sums over other orders
    dense = fine_grid((torch.from_numpy(rows_o), torch.from_numpy(sums_o)), 1, 2)
    assert np.allclose(trunk_o, trunk_i.numpy(), rtol=1e-5, atol=1e-6)
    assert torch.allclose(dense, fine_i, rtol=1e-5, atol=1e-6)


def test_exported_sorted_pooling_gives_the_same_bits_on_every_run(exported_sorted):
    _, proto = exported_sorted
    inputs = _inputs(DEPTHS, seed=3)
    first = _run(proto, inputs, threads=4)
    for _ in range(4):
        assert all(np.array_equal(a, b) for a, b in zip(_run(proto, inputs, threads=4), first))
