"""`occflownet export` plumbing and the fp16/int8 variants (tracing is reused from the session's exported tiny)."""
import json
import re

import numpy as np
import onnx
import pytest

from exported_models import FRAME, SEED, exported_tiny, exported_trained_tiny, frame_available, trained_tiny_checkpoint
from occflownet.export import onnx_export
from occflownet.export.variants import write_variants
from occflownet.cli import main
from occflownet.contract import create_session, decode_metadata
from occflownet.export.parity import DENSITY_TOL, OCCUPANCY_MIN_AGREEMENT
from test_export_onnx import with_class_bias

# one parity line of `occflownet export`'s report (ParityCase.describe)
PARITY_LINE = re.compile(r"density max diff (\S+) \(tol \S+\), occupancy agreement ([0-9.]+)% of (\d+) voxels "
                         r"away from tau -> (ok|FAIL)")


def parity_figures(text: str) -> list[tuple[float, float, int, str]]:
    """(density max diff, occupancy agreement as a fraction, voxels compared, verdict) of every parity line."""
    return [(float(d), float(a) / 100, int(n), v) for d, a, n, v in PARITY_LINE.findall(text)]


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


def test_export_of_a_trained_checkpoint_reports_the_occupancy_figures(tmp_path, capsys, monkeypatch):
    """The trained tiny (occupied voxels) through `occflownet export`: each parity line's agreement, over most of the
    grid, at least OCCUPANCY_MIN_AGREEMENT; its graph with one class's bias raised (σ unchanged): exit 1, nothing
    written, and the lines say why: density within tolerance, agreement below the minimum."""
    graph = exported_trained_tiny()[0]
    ckpt = str(trained_tiny_checkpoint())
    monkeypatch.setattr(onnx_export, "trace_to_onnx", lambda *a, **k: onnx.load(str(graph)))
    assert main(["export", "--checkpoint", ckpt, "--out", str(tmp_path / "ok" / "m.onnx")]) == 0
    figures = parity_figures(capsys.readouterr().out)
    assert len(figures) >= 3 and all(v == "ok" and a >= OCCUPANCY_MIN_AGREEMENT and n > 500_000
                                     for _, a, n, v in figures), figures
    altered = with_class_bias(graph, 1, 100.0, tmp_path / "classes.onnx")
    monkeypatch.setattr(onnx_export, "trace_to_onnx", lambda *a, **k: onnx.load(str(altered)))
    assert main(["export", "--checkpoint", ckpt, "--out", str(tmp_path / "bad" / "m.onnx")]) == 1
    err = capsys.readouterr().err
    figures = parity_figures(err)
    assert "parity failed" in err and not (tmp_path / "bad" / "m.onnx").exists()
    assert figures and all(d <= DENSITY_TOL for d, _, _, _ in figures)
    assert any(v == "FAIL" and a < OCCUPANCY_MIN_AGREEMENT for _, a, _, v in figures), figures


def test_preset_needs_random_init(tmp_path, capsys):
    assert main(["export", "--preset", "tiny", "--out", str(tmp_path / "x.onnx")]) == 2
    assert "--random-init" in capsys.readouterr().err


# one variant's line of `occflownet export --fp16 --int8` (write_variants)
VARIANT_LINE = re.compile(r"occupancy equal ([0-9.]+)% of voxels \(fp32 occupied ([0-9.]+)%\), density max abs diff (\S+)")
# How far the variants of the trained tiny may stray from its fp32 graph: the voxels whose class differs, as a share of
# the voxels fp32 finds occupied (1.4-1.5 %), measured 3.6 % (fp16) and 5.4 % (int8) on the real frame, 6.8 % and
# 5.1 % on the random sample; a variant whose classes or σ went wrong differs on most occupied voxels. Density: max
# |σ - σ_fp32| measured 0.26 (fp16) and 0.05-0.08 (int8) at single voxels; NaN or a σ path gone wrong reaches ~1.
VARIANT_MAX_DIFFERING = 0.2            # of fp32's occupied share
VARIANT_MAX_DENSITY_DIFF = 0.5


def test_fp16_and_int8_variants(tmp_path):
    """The variants of the trained tiny (occupied voxels, so that a class or σ gone wrong shows): each line's figures
    (share of voxels equal to the fp32 graph's, with fp32's occupied share) within the measured bounds."""
    src = tmp_path / "m.onnx"
    src.write_bytes(exported_trained_tiny()[0].read_bytes())
    cfg = exported_trained_tiny()[2].cfg
    lines = write_variants(src, cfg, fp16=True, int8=True, frame=FRAME if frame_available() else None)
    print("\n" + "\n".join(lines))
    figures = [VARIANT_LINE.search(line) for line in lines]
    assert len(lines) == 2 and all(figures), lines
    for tag, line, found in zip(("fp16", "int8"), lines, figures):
        equal, occupied, density = float(found[1]) / 100, float(found[2]) / 100, float(found[3])
        assert f".{tag}.onnx" in line and occupied > 0.005, line       # a grid with things in it
        assert 1.0 - equal <= VARIANT_MAX_DIFFERING * occupied, line
        assert density < VARIANT_MAX_DENSITY_DIFF, line                # NaN fails too
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

    full = write_int8(src, tmp_path / "m.full.onnx", cfg, int8_range="full")
    spans = {}
    for tag, path in (("reduced", tmp_path / "m.int8.onnx"), ("full", full)):
        weights = [onnx.numpy_helper.to_array(i) for i in onnx.load(str(path)).graph.initializer
                   if i.data_type == onnx.TensorProto.INT8 and len(i.dims) == 4]
        spans[tag] = max(int(np.abs(w.astype(np.int32)).max()) for w in weights)
    assert spans["reduced"] <= 64 < spans["full"] <= 127
    with pytest.raises(ValueError, match="int8_range"):
        write_int8(src, tmp_path / "m.bad.onnx", cfg, int8_range="4bit")
    # keep_float replaces the variant's float list: with only the resampling MatMuls kept, the decoder's convolutions
    # are quantised too (benchmarks/studies/int8_sensitivity.py measures such choices)
    from occflownet.export.variants import activation_matmuls

    every = onnx.load(str(write_int8(src, tmp_path / "m.every.onnx", cfg,
                                     keep_float=activation_matmuls(onnx.load(str(src)))))).graph
    producer = {o: n.op_type for n in every.node for o in n.output}
    assert all(producer.get(n.input[1]) == "DequantizeLinear" for n in every.node if n.op_type == "Conv")
