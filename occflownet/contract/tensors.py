"""Contract v1's graph interface: the tensors (names, dtypes, shapes) and the signature check.

Numpy only. The table of tensors and their frames is in :mod:`occflownet.contract`; the inputs a model is fed are
:class:`occflownet.runtime.ModelInputs` (built, checked against :data:`INPUTS` and run there only).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import CAMERAS, GRID

CONTRACT_VERSION = "v1"


class ContractError(ValueError):
    """A model file (or the metadata written into one) breaks contract v1; the message names the file and what."""


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: name, numpy dtype name, shape (None = dynamic dimension)."""

    name: str
    dtype: str
    shape: tuple[int | None, ...]

    @property
    def rank(self) -> int:
        return len(self.shape)

    @property
    def ort_type(self) -> str:
        """The type string onnxruntime reports (``NodeArg.type``)."""
        return {"uint8": "tensor(uint8)", "float32": "tensor(float)"}[self.dtype]

    @property
    def onnx_elem_type(self) -> int:
        """The ``onnx.TensorProto`` element type (UINT8 = 2, FLOAT = 1), without importing onnx."""
        return {"uint8": 2, "float32": 1}[self.dtype]


NUM_CAMERAS = len(CAMERAS)
INPUTS = (TensorSpec("images", "uint8", (None, NUM_CAMERAS, None, None, 3)),
          TensorSpec("intrinsics", "float32", (None, NUM_CAMERAS, 3, 3)),
          TensorSpec("cam2ego", "float32", (None, NUM_CAMERAS, 4, 4)))
OUTPUTS = (TensorSpec("occupancy", "uint8", (None, *GRID.shape)),
           TensorSpec("density", "float32", (None, *GRID.shape)))
INPUT_NAMES = tuple(s.name for s in INPUTS)
OUTPUT_NAMES = tuple(s.name for s in OUTPUTS)


def check_signature(inputs: Sequence[tuple[str, str, Sequence]], outputs: Sequence[tuple[str, str, Sequence]],
                    source: str, exact: bool = False) -> None:
    """Check a graph's inputs/outputs, each given as (name, dtype, shape) with dtype a numpy name ("uint8",
    "float32") or an onnxruntime type string ("tensor(uint8)") and shape entries ints or None/str (dynamic).

    Names, dtypes and ranks must match :data:`INPUTS`/:data:`OUTPUTS` (extra outputs are allowed). ``exact`` also
    requires the same order, nothing extra and the same static dimensions (what ``export`` writes); without it a
    graph may pin a dynamic dimension (e.g. a fixed image size). Raises ContractError naming ``source``.
    """
    for kind, found, specs in (("input", inputs, INPUTS), ("output", outputs, OUTPUTS)):
        by_name = {name: (dtype, list(shape)) for name, dtype, shape in found}
        if exact and [name for name, _, _ in found] != [s.name for s in specs]:
            raise ContractError(f"{source}: graph {kind}s {[n for n, _, _ in found]} differ from contract "
                                f"{CONTRACT_VERSION} {[s.name for s in specs]}")
        for spec in specs:
            if spec.name not in by_name:
                raise ContractError(f"{source}: model has no {kind} '{spec.name}' (has {sorted(by_name)})")
            dtype, shape = by_name[spec.name]
            dims = [d if isinstance(d, int) and not isinstance(d, bool) and d > 0 else None for d in shape]
            ok = dtype in (spec.dtype, spec.ort_type) and len(dims) == spec.rank
            if ok and exact:
                ok = dims == list(spec.shape)
            elif ok:
                ok = all(want is None or got in (None, want) for got, want in zip(dims, spec.shape))
            if not ok:
                raise ContractError(f"{source}: {kind} '{spec.name}' is {dtype} {dims}, contract "
                                    f"{CONTRACT_VERSION} needs {spec.dtype} {list(spec.shape)}")


def session_signature(session) -> tuple[list, list]:
    """(inputs, outputs) of an onnxruntime session as (name, type, shape) triples for :func:`check_signature`."""
    return ([(a.name, a.type, a.shape) for a in session.get_inputs()],
            [(a.name, a.type, a.shape) for a in session.get_outputs()])

