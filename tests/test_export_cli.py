"""`occflownet export` plumbing and the fp16/int8 variants (tracing is reused from the session's exported tiny)."""
import json

import numpy as np
import onnx
import pytest

from exported_models import SEED, exported_tiny
from occflownet.export import onnx_export
from occflownet.export.variants import write_variants
from occflownet.cli import main
from occflownet.contract import create_session, decode_metadata


@pytest.fixture()
def reuse_trace(monkeypatch):
    """Skip torch.onnx tracing: hand back the graph exported (from the seed-SEED tiny) for this session."""
    path = exported_tiny()[0]
    monkeypatch.setattr(onnx_export, "trace_to_onnx", lambda *a, **k: onnx.load(str(path)))
    return path


def test_export_from_checkpoint_and_from_seed(reuse_trace, tmp_path, capsys):
    from occflownet.model import save_checkpoint

    model = exported_tiny()[2]
    ckpt = save_checkpoint(tmp_path / "m.pt", model, model.cfg, {"step": 3})
    assert main(["export", "--checkpoint", str(ckpt), "--out", str(tmp_path / "a.onnx")]) == 0
    assert main(["export", "--preset", "tiny", "--random-init", "--seed", str(SEED),
                 "--out", str(tmp_path / "b.onnx")]) == 0
    assert "parity" in capsys.readouterr().out
    meta = decode_metadata(create_session(tmp_path / "a.onnx").get_modelmeta().custom_metadata_map)
    assert meta["preset"] == "tiny" and meta["onnx_contract"] == "v1"


def test_parity_catches_a_graph_that_is_not_the_model(reuse_trace, tmp_path, capsys):
    """Another seed's weights against the seed-SEED graph: parity fails, nothing is written, exit 1."""
    out = tmp_path / "c.onnx"
    assert main(["export", "--preset", "tiny", "--random-init", "--seed", str(SEED + 1), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "parity failed" in err and "FAIL" in err
    assert list(tmp_path.iterdir()) == []


def test_preset_needs_random_init(tmp_path, capsys):
    assert main(["export", "--preset", "tiny", "--out", str(tmp_path / "x.onnx")]) == 2
    assert "--random-init" in capsys.readouterr().err


def test_fp16_and_int8_variants(tmp_path):
    src = tmp_path / "m.onnx"
    src.write_bytes(exported_tiny()[0].read_bytes())
    lines = write_variants(src, exported_tiny()[2].cfg, fp16=True, int8=True)
    assert len(lines) == 2 and all("occupancy equal" in line for line in lines)
    for tag in ("fp16", "int8"):
        path = tmp_path / f"m.{tag}.onnx"
        proto = onnx.load(str(path))
        onnx.checker.check_model(proto)
        assert {n.domain for n in proto.graph.node} == {""} and proto.ir_version <= 13
        meta = {p.key: json.loads(p.value) for p in proto.metadata_props}
        assert meta["precision"] == tag and meta["onnx_contract"] == "v1"
        session = create_session(path)
        assert [i.name for i in session.get_inputs()] == ["images", "intrinsics", "cam2ego"]
    ops = {n.op_type for n in onnx.load(str(tmp_path / "m.int8.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    # the image convolutions are quantised, the 3D decoder's (downstream of the voxel pooling) stay float32
    from occflownet.export.variants import voxel_convs

    fp32_convs = [n.name for n in onnx.load(str(src)).graph.node if n.op_type == "Conv"]
    in_grid = set(voxel_convs(onnx.load(str(src))))
    assert in_grid and len(in_grid) < len(fp32_convs)
    int8 = onnx.load(str(tmp_path / "m.int8.onnx")).graph
    producer = {o: n.op_type for n in int8.node for o in n.output}
    quantised = {n.name: producer.get(n.input[1]) == "DequantizeLinear" for n in int8.node if n.op_type == "Conv"}
    assert sorted(quantised) == sorted(fp32_convs)
    assert all(quantised[name] != (name in in_grid) for name in fp32_convs)
    # int8_range: 7-bit weights (the default, exact on any x86 CPU) span at most ±64, 8-bit ones use the full ±127
    from occflownet.export.variants import write_int8

    full = write_int8(src, tmp_path / "m.full.onnx", exported_tiny()[2].cfg, int8_range="full")
    spans = {}
    for tag, path in (("reduced", tmp_path / "m.int8.onnx"), ("full", full)):
        weights = [onnx.numpy_helper.to_array(i) for i in onnx.load(str(path)).graph.initializer
                   if i.data_type == onnx.TensorProto.INT8 and len(i.dims) == 4]
        spans[tag] = max(int(np.abs(w.astype(np.int32)).max()) for w in weights)
    assert spans["reduced"] <= 64 < spans["full"] <= 127
    with pytest.raises(ValueError, match="int8_range"):
        write_int8(src, tmp_path / "m.bad.onnx", exported_tiny()[2].cfg, int8_range="4bit")
    # keep_float replaces the variant's float list: with only the resampling MatMuls kept, the decoder's convolutions
    # are quantised too (benchmarks/int8_sensitivity.py measures such choices)
    from occflownet.export.variants import activation_matmuls

    every = onnx.load(str(write_int8(src, tmp_path / "m.every.onnx", exported_tiny()[2].cfg,
                                     keep_float=activation_matmuls(onnx.load(str(src)))))).graph
    producer = {o: n.op_type for n in every.node for o in n.output}
    assert all(producer.get(n.input[1]) == "DequantizeLinear" for n in every.node if n.op_type == "Conv")
    diffs = [float(line.rsplit("diff ", 1)[1]) for line in lines]
    assert max(diffs) < 0.05 and not np.isnan(diffs).any()
