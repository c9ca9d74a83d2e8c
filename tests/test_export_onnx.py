"""The exported tiny graph: contract v1, metadata, validity, parity (real frame, random, batch 1/2, two rigs)."""
import json

import numpy as np
import onnx
import pytest
import torch

from exported_models import FRAME, exported_tiny, exported_trained_tiny, frame_available
from occflownet.export import onnx_export, parity
from occflownet.export.parity import (DENSITY_TOL, OCCUPANCY_MIN_AGREEMENT, THRESHOLD_BAND, check_parity, compare,
                                      default_parity_samples, frame_sample)
from occflownet import __version__
from occflownet.model.decoder import slab_width
from occflownet.occ3d import CAMERAS, CLASS_COLORS, CLASS_NAMES, GRID
from occflownet.contract import METADATA_KEYS, create_session, decode_metadata
from occflownet.runtime import ModelInputs, OnnxPredictor, TorchPredictor
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig


@pytest.fixture(scope="module")
def exported():
    return exported_tiny()


@pytest.fixture(scope="module")
def trained():
    """The trained tiny (occupied voxels of several classes), exported with the parity check."""
    return exported_trained_tiny()


def with_class_bias(path, cls: int, shift: float, out):
    """A copy of the exported graph at ``path`` with ``shift`` added to Φs's output bias of class ``cls`` (the density
    path untouched), written to ``out``: a graph that agrees with the model on σ and not on the classes."""
    proto = onnx.load(str(path))
    [init] = [i for i in proto.graph.initializer if i.name.endswith("decoder.semantic_head.2.bias")]
    bias = onnx.numpy_helper.to_array(init).copy()
    bias[cls] += shift
    init.CopyFrom(onnx.numpy_helper.from_array(bias, init.name))
    onnx.save(proto, str(out))
    return out


def test_compare_counts_the_voxels_away_from_tau_by_hand():
    """Known answers: 32,000 voxels, 2,000 of them within THRESHOLD_BAND of τ (their flips do not count), so 30,000
    are compared; one class flip among them passes (29,999 / 30,000 ≥ 99.99 %), four fail."""
    tau = 0.35
    dens_t = np.full(32_000, 0.9, np.float32)
    dens_t[:1000], dens_t[1000:2000] = tau + 0.5 * THRESHOLD_BAND, tau - 0.5 * THRESHOLD_BAND
    dens_t[2000:12_000] = 0.1                                        # free, away from τ
    occ_t = np.where(dens_t >= tau, 4, 17).astype(np.uint8)
    dens_o = dens_t.copy()
    dens_o[20_000] += 6e-5
    occ_o = occ_t.copy()
    occ_o[:2000] = np.where(occ_t[:2000] == 17, 4, 17)               # every voxel in the band flips
    one, four = occ_o.copy(), occ_o.copy()
    one[30_000] = 11
    four[[30_000, 30_001, 2000, 2001]] = [11, 11, 4, 4]              # two classes, two free voxels made occupied
    a, b = compare(occ_t, dens_t, one, dens_o, tau), compare(occ_t, dens_t, four, dens_o, tau)
    assert a.voxels_compared == b.voxels_compared == 30_000
    assert a.density_max_abs_diff == pytest.approx(6e-5, rel=1e-3)
    assert a.occupancy_agreement == pytest.approx(29_999 / 30_000, abs=1e-12) and a.ok
    assert b.occupancy_agreement == pytest.approx(29_996 / 30_000, abs=1e-12) and not b.ok
    assert "FAIL" in b.describe() and "99.9867%" in b.describe()


def test_trained_export_agrees_on_occupied_voxels(trained):
    """The parity figures of the trained model's export: every sample compares tens of thousands of voxels, a share
    of them occupied, and agrees on at least OCCUPANCY_MIN_AGREEMENT of them."""
    path, result, model = trained
    assert all(c.ok for c in result.parity), result.summary()
    for case in result.parity:
        voxels = case.shape[0] * 200 * 200 * 16                      # batch × the grid
        assert case.occupancy_agreement >= OCCUPANCY_MIN_AGREEMENT and case.voxels_compared > 0.9 * voxels, \
            case.describe()
        assert case.density_max_abs_diff <= DENSITY_TOL
    sample = default_parity_samples(model.cfg)[0]
    occ, _ = OnnxPredictor.open(path)(sample.inputs)
    assert 0.005 < np.mean(occ != 17)                                # a grid with things in it


def test_parity_fails_a_graph_whose_classes_differ_by_the_occupancy_figure(trained, tmp_path):
    """Φs's output bias of one class raised by 100 in the graph only: σ is the model's (density within tolerance)
    and every voxel ONNX finds occupied takes that class, so parity must fail on the occupancy agreement, whose
    value is known from torch's grid: the share of compared voxels torch finds free or of that class."""
    path, _, model = trained
    cls = 1                                                          # barrier
    altered = with_class_bias(path, cls, 100.0, tmp_path / "classes.onnx")
    samples = default_parity_samples(model.cfg)[:1] + ([frame_sample(FRAME, 1)] if frame_available() else [])
    for sample, case in zip(samples, check_parity(model, altered, samples, model.cfg.threshold)):
        occ_t, dens_t = TorchPredictor(model)(sample.inputs)
        away = np.abs(dens_t - model.cfg.threshold) > THRESHOLD_BAND
        expected = float(np.mean(np.isin(occ_t[away], (17, cls))))
        assert expected < 0.999, (sample.name, expected)              # occupied voxels of other classes to flip
        assert case.density_max_abs_diff <= DENSITY_TOL, case.describe()
        assert case.occupancy_agreement == pytest.approx(expected, abs=1e-9), case.describe()
        assert not case.ok and "FAIL" in case.describe()


def test_export_reports_parity_on_every_required_case(exported):
    _, result, _ = exported
    names = [c.name for c in result.parity]
    assert all(c.ok for c in result.parity), result.summary()
    assert any("b2" in n or "+turned" in n for n in names)             # batch 2
    assert any("two-rigs" in n for n in names)                           # two calibrations
    if frame_available():
        assert "frame:nuscenes-frame" in names and "frame:nuscenes-frame+turned-rig" in names
        assert "frame:nuscenes-frame@1/4" in names                       # as predict/serve/C++ decode it (tiny)


def test_graph_is_standard_onnx_with_contract_v1_io(exported):
    path, _, model = exported
    proto = onnx.load(str(path))
    onnx.checker.check_model(proto, full_check=True)
    assert {n.domain for n in proto.graph.node} == {""}
    assert len(proto.functions) == 0
    assert 8 <= proto.ir_version <= 13
    assert [o.domain for o in proto.opset_import] == [""]
    dims = {v.name: [d.dim_value or d.dim_param for d in v.type.tensor_type.shape.dim]
            for v in list(proto.graph.input) + list(proto.graph.output)}
    assert dims == {"images": ["batch", 6, "height", "width", 3], "intrinsics": ["batch", 6, 3, 3],
                    "cam2ego": ["batch", 6, 4, 4], "occupancy": ["batch", 200, 200, 16],
                    "density": ["batch", 200, 200, 16]}
    types = {v.name: v.type.tensor_type.elem_type for v in list(proto.graph.input) + list(proto.graph.output)}
    assert types["images"] == types["occupancy"] == onnx.TensorProto.UINT8
    assert types["density"] == types["intrinsics"] == types["cam2ego"] == onnx.TensorProto.FLOAT
    scatters = sorted((n.op_type, next((a.s.decode() for a in n.attribute if a.name == "reduction"), "none"))
                      for n in proto.graph.node if n.op_type.startswith("Scatter"))
    # no scatter adds (onnxruntime's ScatterND(add) races across threads, its ScatterElements(add) is
    # single-threaded): the pooling sums by sorted segment sums and writes each trunk cell once; each slab of the
    # per-voxel chain writes its skip features to their own rows and its labels to the selected rows of its occupied
    # voxels: 1 + 2 per slab reduction-less ScatterND on unique indices
    cfg = model.cfg
    xc, yc, zc = cfg.trunk_grid
    per = yc * zc * cfg.decoder_stride ** 3
    slabs = -(-xc // slab_width(xc, per, model.decoder.widest))
    assert slabs > 1 and scatters == [("ScatterND", "none")] * (1 + 2 * slabs)


class _Picks(torch.nn.Module):
    """x [N], y [N, 3] → the positions of x's non-zero entries (torch.nonzero of a 1-D tensor) and y's ([K, 2])."""

    def forward(self, x, y):
        return torch.nonzero(x > 0.5).reshape(-1), torch.nonzero(y > 0.5)


def test_nonzero_exports_as_compress_with_torchs_positions(tmp_path):
    from onnx.reference import ReferenceEvaluator

    x, y = torch.rand(50), torch.rand(40, 3)
    n = torch.export.Dim("n", min=2, max=4096)
    proto = onnx_export.trace_to_onnx(_Picks(), (x, y), tmp_path / "picks.onnx", ["x", "y"], ["rows", "cells"],
                                      {"x": {0: n}, "y": {0: torch.export.Dim("m", min=2, max=4096)}})
    ops = [node.op_type for node in proto.graph.node]
    assert ops.count("Compress") == 1 and ops.count("NonZero") == 1          # 1-D: Compress; 2-D: NonZero
    session = create_session(tmp_path / "picks.onnx", check_contract=False)
    reference = ReferenceEvaluator(proto)
    for size, fraction in [(50, 0.5), (3000, 0.1), (7, 0.0), (9, 1.0)]:
        x = (torch.rand(size) < fraction).float()
        y = torch.rand(size + 3, 3)
        want = [t.numpy() for t in _Picks()(x, y)]
        for got in (session.run(None, {"x": x.numpy(), "y": y.numpy()}),
                    reference.run(None, {"x": x.numpy(), "y": y.numpy()})):
            assert [g.dtype for g in got] == [np.int64, np.int64]
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])


def test_graph_selects_without_nonzero_and_ends_with_occupancy(exported):
    path, _, _ = exported
    nodes = list(onnx.load(str(path)).graph.node)
    assert "NonZero" not in {n.op_type for n in nodes} and any(n.op_type == "Compress" for n in nodes)
    # onnxruntime walks back from the last output node: occupancy's Concat last runs each slab's Φs after its σ
    producer = {out: i for i, n in enumerate(nodes) for out in n.output}
    assert producer["density"] < producer["occupancy"] == len(nodes) - 1


def test_metadata(exported):
    path, _, model = exported
    meta = decode_metadata(create_session(path).get_modelmeta().custom_metadata_map)
    assert set(METADATA_KEYS) <= set(meta)
    assert meta["classes"] == list(CLASS_NAMES) and meta["free_index"] == 17
    assert meta["grid"] == GRID.to_dict() and meta["cameras"] == list(CAMERAS)
    assert meta["class_colors"] == CLASS_COLORS.tolist()
    assert meta["threshold"] == 0.35 and meta["input_size"] == [160, 288] and meta["preset"] == "tiny"
    assert meta["default_calibration"] == json.loads(json.dumps(default_rig(480, 270)))
    assert meta["default_calibration"]["image_size"] == [480, 270]
    assert meta["occflownet_version"] == __version__ and meta["onnx_contract"] == "v1"
    raw = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert all(json.loads(raw[k]) == meta[k] for k in METADATA_KEYS)     # JSON-encoded values


@pytest.mark.skipif(not frame_available(), reason=f"real frame not found at {FRAME}")
def test_parity_on_the_real_frame_with_argmax_in_play(exported):
    """Shift Φσ's output bias so that σ straddles τ and zero Φs's output bias (same change in torch and in the ONNX
    initializers): about half the voxels are occupied and the argmax over 17 logits varies, batch 1 and 2."""
    path, _, model = exported
    model = __import__("copy").deepcopy(model)
    sample = frame_sample(FRAME, 2)
    with torch.no_grad():
        dens = model.inference(*(torch.from_numpy(a[:1]) for a in (sample.images, sample.intrinsics,
                                                                    sample.cam2ego)))[1]
        median = float(torch.logit(dens).median())
        bias = model.decoder.sigma_head[-1].bias
        bias += float(np.log(0.35 / 0.65)) - median
        model.decoder.semantic_head[-1].bias.zero_()
    proto = onnx.load(str(path))
    for init in proto.graph.initializer:
        if init.name.startswith("model.decoder.") and init.name.endswith("_head.2.bias"):
            value = model.get_parameter(init.name.removeprefix("model.")).detach().numpy().astype(np.float32)
            init.CopyFrom(onnx.numpy_helper.from_array(value, init.name))
    shifted = path.parent / "tiny_shifted.onnx"
    onnx.save(proto, str(shifted))
    cases = check_parity(model, shifted, [frame_sample(FRAME, 1), sample], model.cfg.threshold)
    assert all(c.ok for c in cases), [c.describe() for c in cases]
    occ, _ = OnnxPredictor.open(shifted)(sample.inputs)
    occupied = np.mean(occ != 17)
    assert 0.2 < occupied < 0.8 and len(np.unique(occ)) >= 3      # free + several classes


def test_dynamic_batch_and_image_size(trained):
    """Batch 3 at 200×128, another size than the export's: the trained model (occupied voxels) agrees with torch."""
    path, _, model = trained
    session = create_session(path)
    K, T = calibration_arrays(default_rig(200, 128))
    rng = np.random.default_rng(3)
    images = rng.integers(0, 256, (3, 6, 128, 200, 3), dtype=np.uint8)
    Ks, Ts = np.stack([K] * 3), np.stack([T] * 3)
    occ, dens = OnnxPredictor(session)(ModelInputs(images, Ks, Ts))
    assert occ.shape == (3, 200, 200, 16) and occ.dtype == np.uint8 and dens.dtype == np.float32
    with torch.no_grad():
        occ_t, dens_t = model.inference(torch.from_numpy(images), torch.from_numpy(Ks), torch.from_numpy(Ts))
    case = compare(occ_t.numpy(), dens_t.numpy(), occ, dens, model.cfg.threshold, "dyn", images.shape)
    assert case.ok and case.occupancy_agreement >= OCCUPANCY_MIN_AGREEMENT, case.describe()
    assert np.mean(occ != 17) > 0.001 and case.voxels_compared > 0.9 * occ.size      # occupied voxels compared


def test_parity_failure_writes_nothing(exported, tmp_path, monkeypatch):
    path, _, model = exported
    proto = onnx.load(str(path))
    monkeypatch.setattr(onnx_export, "trace_to_onnx", lambda *a, **k: proto)   # skip re-tracing (slow)
    monkeypatch.setattr(parity, "DENSITY_TOL", -1.0)                           # no graph can pass this
    out = tmp_path / "model.onnx"
    samples = default_parity_samples(model.cfg)[:1]
    with pytest.raises(onnx_export.ExportError, match="parity failed"):
        onnx_export.export_model(model, model.cfg, out, parity_samples=samples)
    assert list(tmp_path.iterdir()) == []


def test_non_standard_domain_is_rejected(exported):
    proto = onnx.load(str(exported[0]))
    proto.graph.node[0].domain = "com.microsoft"
    with pytest.raises(onnx_export.ExportError):
        onnx_export.validate_proto(proto)
