"""The onnxruntime session of a contract-v1 model: made and checked in one place.

onnxruntime is imported when a session is made, never torch. Run only by :class:`occflownet.runtime.OnnxPredictor`
(predict, eval ``--model``, export parity and variants, the server, the benchmarks).
"""
from __future__ import annotations

import os
from pathlib import Path

from occflownet.contract.metadata import ModelMetadata, parse_metadata
from occflownet.contract.tensors import check_signature, session_signature


def check_session(session, source: str) -> ModelMetadata:
    """Signature and metadata of an onnxruntime session against contract v1 → its :class:`ModelMetadata`."""
    check_signature(*session_signature(session), source)
    return parse_metadata(dict(session.get_modelmeta().custom_metadata_map), source)


def create_session(model_path: str | Path, threads: int | None = None, spinning: bool = False,
                   providers: list[str] | None = None, check_contract: bool = True):
    """An onnxruntime session (CPU by default) with ``threads`` intra-op threads (default: all cores), checked
    against contract v1 (inputs, outputs, metadata) unless ``check_contract=False``.

    ``spinning=False`` lets idle worker threads sleep instead of busy-waiting: on a loaded machine (a server
    sharing its cores, several processes) this cut tiny's p50 from 172 to 125 ms in our measurements; on an idle
    machine spinning can be a few percent faster. Raises FileNotFoundError, ValueError (cannot load) or
    ContractError (a ValueError), each naming the file."""
    import onnxruntime as ort

    model_path = Path(model_path)
    if not model_path.is_file():
        raise FileNotFoundError(f"ONNX model not found: {model_path}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    try:
        session = ort.InferenceSession(str(model_path), so, providers=providers or ["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
        raise ValueError(f"{model_path}: onnxruntime cannot load this model ({type(exc).__name__}: {exc})") from exc
    if check_contract:
        check_session(session, str(model_path))
    return session

