"""Export an :class:`~occflownet.model.OccupancyModel` to one ONNX file (contract v1) with a parity check.

Pipeline (nothing is written to ``out`` unless every step passes):
1. ``torch.onnx.export(dynamo=True)`` of :class:`~occflownet.model.InferenceGraph` (preprocessing, backbone, lift,
   decoder, fusion) with dynamic batch, height and width, opset 18, ``torch.nonzero`` of a 1-D tensor written as
   ``Compress`` (:func:`nonzero_as_compress`). The dynamo exporter writes the voxel pooling
   (``index_add``) as ``ScatterND(reduction="add")``; the TorchScript exporter's reduction-less ScatterND is wrong
   for repeated voxel indices.
2. Clean-up (exporter node annotations dropped), every ``ScatterND(reduction="add")`` rewritten as an equivalent
   ``ScatterElements(axis=0, reduction="add")`` (:func:`deterministic_scatter_add`: onnxruntime's ScatterND
   splits the updates over its intra-op threads and adds without synchronisation, so repeated voxel indices race
   and lose updates at random; its ScatterElements adds in index order on one thread, exactly like torch's
   ``index_add``), ``metadata_props`` (JSON values, keys ``contract.METADATA_KEYS``), IR version capped at
   ``MAX_IR_VERSION`` for onnxruntime 1.31.
3. ``onnx.checker`` (full check), every node in the standard domain, inputs/outputs as in contract v1.
4. onnxruntime loads it and must agree with torch on every parity sample (``parity.py``): density within 1e-4
   absolute, occupancy equal on ≥ 99.99 % of the voxels whose σ is not within 1e-3 of τ.
5. Temp file in the destination folder + ``os.replace`` (``occflownet.files.atomic_path``).
"""
from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
import torch

from occflownet import __version__, contract
from occflownet.occ3d import CAMERAS, CLASS_COLORS, CLASS_NAMES, FREE, GRID
from occflownet.contract import CONTRACT_VERSION as CONTRACT
from occflownet.contract import INPUT_NAMES, OUTPUT_NAMES, calibration_arrays
from occflownet.files import atomic_path
from occflownet.model import InferenceGraph, ModelConfig, OccupancyModel

from occflownet.export.parity import ParityCase, ParitySample, check_parity, default_parity_samples

OPSET = 18
MAX_IR_VERSION = 10  # onnxruntime 1.31 reads IR <= 13; opset 18 needs IR >= 8


class ExportError(RuntimeError):
    """Export failed (validation or parity); no file was written."""


@dataclass
class ExportResult:
    path: Path
    parity: list[ParityCase] = field(default_factory=list)
    seconds: float = 0.0
    metadata: dict = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"wrote {self.path} ({self.path.stat().st_size / 1e6:.1f} MB) in {self.seconds:.1f} s"]
        lines += [f"  parity {c.describe()}" for c in self.parity]
        return "\n".join(lines)


def contract_metadata(cfg: ModelConfig, extra: dict | None = None) -> dict:
    """The metadata_props of contract v1 (values are JSON-encoded when written), checked by the contract's own
    parser (``contract.parse_metadata``) so that every consumer can read what export writes."""
    calib = dict(cfg.default_calibration)
    if "image_size" not in calib:
        raise ExportError("the model config's default_calibration lacks 'image_size' [w, h]")
    meta = {
        "classes": list(CLASS_NAMES),
        "free_index": FREE,
        "grid": GRID.to_dict(),
        "cameras": list(CAMERAS),
        "class_colors": CLASS_COLORS.astype(int).tolist(),
        "threshold": float(cfg.threshold),
        "input_size": list(cfg.input_size),
        "preset": cfg.preset,
        "default_calibration": calib,
        "occflownet_version": __version__,
        "onnx_contract": CONTRACT,
        "model_config": cfg.to_dict(),
    }
    meta.update(extra or {})
    missing = [k for k in contract.METADATA_KEYS if k not in meta]
    try:
        if missing:
            raise contract.ContractError(f"metadata lacks {missing}")
        contract.parse_metadata(contract.encode_metadata(meta), "the exported metadata")
    except contract.ContractError as exc:
        raise ExportError(str(exc)) from None
    return meta


def example_inputs(cfg: ModelConfig, batch: int = 2):
    """Tracing inputs: random uint8 images at the default calibration's size, batch 2 (so B is not specialised)."""
    w, h = cfg.default_calibration["image_size"]
    K, T = calibration_arrays(cfg.default_calibration)
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (batch, len(CAMERAS), int(h), int(w), 3), dtype=torch.uint8, generator=g)
    return (images, torch.from_numpy(K)[None].repeat(batch, 1, 1, 1),
            torch.from_numpy(T)[None].repeat(batch, 1, 1, 1))


def nonzero_as_compress(x):
    """The exporter's translation of ``torch.nonzero``: of a 1-D ``x`` [N] → int64 [K, 1], the positions 0 .. N − 1
    kept where ``x`` is non-zero (ONNX ``Compress`` of a ``Range``), in ascending order as ``NonZero`` gives them;
    onnxruntime's NonZero runs about twice as long (a slab's 64,000 σ of tiny: docs/results.md#inference). Other
    ranks: ``NonZero`` transposed to torch's [K, rank]."""
    from onnxscript import opset18 as op

    if x.shape is None or len(x.shape) != 1:
        return op.Transpose(op.NonZero(x), perm=[1, 0])
    positions = op.Range(op.Constant(value_int=0), op.Squeeze(op.Shape(x)), op.Constant(value_int=1))
    return op.Unsqueeze(op.Compress(positions, op.Cast(x, to=onnx.TensorProto.BOOL), axis=0),
                        op.Constant(value_ints=[1]))


def trace_to_onnx(module: torch.nn.Module, inputs: tuple, path: Path, input_names, output_names,
                  dynamic_shapes) -> onnx.ModelProto:
    """torch.onnx.export(dynamo=True) into ``path``, returned as a ModelProto (exporter chatter silenced)."""
    loggers = [logging.getLogger(n) for n in ("onnx_ir", "onnxscript", "torch.onnx", "torch.export")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            torch.onnx.export(module, inputs, str(path), dynamo=True, opset_version=OPSET, verbose=False,
                              input_names=list(input_names), output_names=list(output_names),
                              dynamic_shapes=dynamic_shapes, external_data=False,
                              custom_translation_table={torch.ops.aten.nonzero.default: nonzero_as_compress})
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
    return onnx.load(str(path))


def deterministic_scatter_add(proto: onnx.ModelProto) -> int:
    """Rewrite, in place, each ``ScatterND(data [R, C], indices [N, 1], updates [N, C], reduction="add")`` as a
    1-D ``ScatterElements(data [R·C], indices·C + [0 .. C) [N·C], updates [N·C], axis=0, reduction="add")``
    (:func:`_flat_scatter_add`); returns the number of nodes rewritten.

    Both compute ``data[indices[i, 0], c] += updates[i, c]``. Why: onnxruntime's CPU ScatterND (1.32) hands blocks of
    ``indices`` to its intra-op threads and adds with plain read-modify-writes, so two threads hitting the same voxel
    can lose an update — measured on a synthetic pooling (69,120 updates into 200 rows, 2 threads): 5 of 20 runs
    wrong by up to 14.7 (whole updates lost), on the trained tiny export density errors of 1e-3–5e-3 at random.
    Its ScatterElements kernel is single-threaded and adds in index order, which is also the order of torch's CPU
    ``index_add``: the pooled sums are bit-identical to torch's on every run. The 1-D form adds the same values in
    the same order, but onnxruntime's kernel walks a 1-D index about 4x faster than the 2-D one (per-element offset
    arithmetic over one axis instead of two; measured 135 vs 35 ms for 34,560 x 32 updates on the loaded 2-core
    machine, docs/results.md#inference). Only the 2-D pooling form the
    exporter writes for ``index_add`` is accepted; any other ScatterND with a reduction is an ExportError.
    """
    inferred = onnx.shape_inference.infer_shapes(proto).graph
    dims = {v.name: [d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim]
            for v in list(inferred.value_info) + list(inferred.input) + list(inferred.output)
            if v.type.HasField("tensor_type") and v.type.tensor_type.HasField("shape")}
    nodes, rewritten = [], 0
    for node in proto.graph.node:
        reduction = next((a.s.decode() for a in node.attribute if a.name == "reduction"), "none")
        if node.op_type != "ScatterND" or reduction == "none":
            nodes.append(node)
            continue
        data, indices, updates = (dims.get(name) for name in node.input)
        if data is None or indices is None or updates is None or len(data) != 2 or indices[1:] != [1] \
                or len(updates) != 2:
            raise ExportError(f"ScatterND {node.name!r} (reduction {reduction}) is not the 2-D pooling form "
                              f"data [R, C], indices [N, 1], updates [N, C] (got {data}, {indices}, {updates}); "
                              "cannot make it deterministic")
        nodes += _flat_scatter_add(node, node.name or f"scatter_add_{rewritten}", reduction)
        rewritten += 1
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)
    return rewritten


def _flat_scatter_add(node: onnx.NodeProto, base: str, reduction: str) -> list[onnx.NodeProto]:
    """The nodes of one pooling ScatterND(data [R, C], indices [N, 1], updates [N, C]) as a 1-D ScatterElements:
    ``flat = indices · C + [0 .. C)`` [N, C] → [N·C]; data and updates flattened (Reshape, no copy); the result
    reshaped to data's shape. Element ``(i, c)`` of the updates lands on ``indices[i]·C + c`` in the order of
    the flattened updates, so every output element receives its updates in increasing i: the order of the 2-D
    form and of torch's ``index_add``."""
    data, indices, updates = node.input
    make = onnx.helper.make_node
    t = {k: f"{base}_{k}" for k in ("c", "c0", "zero", "one", "range", "rows", "flat2", "flat", "minus1",
                                    "data1", "updates1", "out1", "data_shape")}
    const = [(t["zero"], 0), (t["one"], 1)]
    nodes = [make("Constant", [], [name], name=name, value=onnx.helper.make_tensor(name, onnx.TensorProto.INT64,
                                                                                   [], [v])) for name, v in const]
    nodes.append(make("Constant", [], [t["minus1"]], name=t["minus1"],
                      value=onnx.helper.make_tensor(t["minus1"], onnx.TensorProto.INT64, [1], [-1])))
    nodes += [
        make("Shape", [updates], [t["c"]], name=t["c"], start=1, end=2),                    # [C]
        make("Squeeze", [t["c"]], [t["c0"]], name=t["c0"]),                                 # C
        make("Range", [t["zero"], t["c0"], t["one"]], [t["range"]], name=t["range"]),      # [C]
        make("Mul", [indices, t["c"]], [t["rows"]], name=t["rows"]),                        # [N, 1]
        make("Add", [t["rows"], t["range"]], [t["flat2"]], name=t["flat2"]),               # [N, C]
        make("Reshape", [t["flat2"], t["minus1"]], [t["flat"]], name=t["flat"]),           # [N·C]
        make("Reshape", [data, t["minus1"]], [t["data1"]], name=t["data1"]),               # [R·C]
        make("Reshape", [updates, t["minus1"]], [t["updates1"]], name=t["updates1"]),      # [N·C]
        make("ScatterElements", [t["data1"], t["flat"], t["updates1"]], [t["out1"]], name=f"{base}_elements",
             axis=0, reduction=reduction),
        make("Shape", [data], [t["data_shape"]], name=t["data_shape"]),
        make("Reshape", [t["out1"], t["data_shape"]], list(node.output), name=f"{base}_reshape"),
    ]
    return nodes


def portable_resize(proto: onnx.ModelProto) -> None:
    """Drop ``antialias=0`` (the default) from Resize nodes, so that no ``antialias`` attribute is left for a runtime
    to misread; an ``antialias=1`` Resize is an ExportError (OpenVINO ignores it silently, TensorRT's parser and
    others have their own gaps; the model's preprocessing writes the antialiasing filter out instead)."""
    for node in proto.graph.node:
        if node.op_type != "Resize":
            continue
        kept = [a for a in node.attribute if not (a.name == "antialias" and a.i == 0)]
        if any(a.name == "antialias" for a in kept):
            raise ExportError(f"Resize {node.name!r} has antialias=1, which runtimes compute differently; contract v1 "
                              "graphs write antialiasing as explicit filters")
        del node.attribute[:]
        node.attribute.extend(kept)


def finalize_proto(proto: onnx.ModelProto, metadata: dict | None) -> onnx.ModelProto:
    """Drop exporter annotations, make scatter-adds deterministic, write metadata, cap the IR version; validate
    (checker + standard domain)."""
    for node in proto.graph.node:
        del node.metadata_props[:]
        node.doc_string = ""
    for vi in list(proto.graph.input) + list(proto.graph.output):
        del vi.metadata_props[:]
    proto.doc_string = ""
    deterministic_scatter_add(proto)
    portable_resize(proto)
    del proto.metadata_props[:]
    for key, value in contract.encode_metadata(metadata or {}).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.ir_version = min(proto.ir_version, MAX_IR_VERSION)
    validate_proto(proto)
    return proto


def validate_proto(proto: onnx.ModelProto) -> None:
    """onnx.checker (full), standard-domain nodes only, no local functions; ExportError otherwise."""
    try:
        onnx.checker.check_model(proto, full_check=True)
    except Exception as exc:
        raise ExportError(f"onnx.checker rejected the exported graph: {exc}") from exc
    foreign = sorted({n.domain for n in proto.graph.node if n.domain not in ("", "ai.onnx")})
    if foreign or len(proto.functions):
        raise ExportError(f"graph uses non-standard domains {foreign} or local functions "
                          f"({len(proto.functions)}); contract v1 allows standard ONNX operators only")
    if proto.ir_version > MAX_IR_VERSION:
        raise ExportError(f"IR version {proto.ir_version} > {MAX_IR_VERSION}")


def check_io(proto: onnx.ModelProto) -> None:
    """Inputs/outputs exactly as contract v1 (names and order, element types, ranks, static dims); ExportError."""
    dtypes = {onnx.TensorProto.UINT8: "uint8", onnx.TensorProto.FLOAT: "float32"}

    def triples(values):
        return [(v.name, dtypes.get(v.type.tensor_type.elem_type, str(v.type.tensor_type.elem_type)),
                 [d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim])
                for v in values]

    try:
        contract.check_signature(triples(proto.graph.input), triples(proto.graph.output), "exported graph",
                                 exact=True)
    except contract.ContractError as exc:
        raise ExportError(str(exc)) from None


def export_model(model: OccupancyModel, cfg: ModelConfig, out: str | Path, *,
                 parity_samples: list[ParitySample] | None = None, parity_frames: list | None = None,
                 extra_metadata: dict | None = None) -> ExportResult:
    """Export ``model`` (built from ``cfg``) to ``out``; raises ExportError (and writes nothing) on any failure.

    ``parity_samples``: explicit torch-vs-onnxruntime samples; default: ``default_parity_samples(cfg,
    parity_frames)`` (random images at two sizes and two calibrations, batch 1 and 2, plus each real frame
    folder in ``parity_frames``).
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    if parity_samples is None:
        parity_samples = default_parity_samples(cfg, parity_frames or [])
    batch = torch.export.Dim("batch", min=1, max=1024)
    height = torch.export.Dim("height", min=32, max=16384)
    width = torch.export.Dim("width", min=32, max=16384)
    dynamic = {"images": {0: batch, 2: height, 3: width}, "intrinsics": {0: batch}, "cam2ego": {0: batch}}
    with atomic_path(out) as tmp:
        proto = trace_to_onnx(InferenceGraph(model).eval(), example_inputs(cfg), tmp, INPUT_NAMES, OUTPUT_NAMES,
                              dynamic)
        metadata = contract_metadata(cfg, extra_metadata)
        proto = finalize_proto(proto, metadata)
        check_io(proto)
        onnx.save(proto, str(tmp))
        cases = check_parity(model, tmp, parity_samples, cfg.threshold)
        failed = [c for c in cases if not c.ok]
        if failed:
            raise ExportError("torch/onnxruntime parity failed, nothing written:\n  "
                              + "\n  ".join(c.describe() for c in failed))
    return ExportResult(out, cases, time.perf_counter() - t0, metadata)


def agreement(occ_a: np.ndarray, dens_a: np.ndarray, occ_b: np.ndarray, dens_b: np.ndarray) -> dict:
    """Agreement figures between two predictions (e.g. fp32 vs fp16/int8 variants)."""
    return {"occupancy_equal_fraction": float(np.mean(occ_a == occ_b)),
            "density_max_abs_diff": float(np.max(np.abs(dens_a.astype(np.float32) - dens_b.astype(np.float32))))}
