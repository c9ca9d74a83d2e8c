"""Contract v1 as a C++17 header for ``embed/``: the C++ runner's names, dtypes, ranks, fixed dimensions, metadata
keys and calibration tolerances, rendered from this package's definitions so that no C++ file restates them.

    python -m occflownet.contract.cpp_header            # (re)write embed/include/occflownet/contract_v1.hpp
    python -m occflownet.contract.cpp_header --check    # exit 1 when the checked-in header differs

Run from the repository root (or give ``--out``). The header is checked into ``embed/``, so building the C++ needs
no Python; ``tests/test_contract_cpp_header.py`` fails while the checked-in file differs from :func:`render_header`.
Every value comes from :mod:`occflownet.contract` (``INPUTS``, ``OUTPUTS``, ``METADATA_KEYS``,
``REQUIRED_METADATA_KEYS``, ``CONTRACT_VERSION``, ``NUM_CAMERAS``, the calibration tolerances and limits) and
:mod:`occflownet.occ3d` (grid shape, classes, free index). Torch-free: numpy and the standard library only.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from occflownet.contract.calibration import (ASPECT_TOLERANCE, FLOAT32_LIMIT, MAX_CALIBRATION_BYTES,
                                             MAX_CALIBRATION_DEPTH, MAX_IMAGE_SIDE, ORTHONORMAL_TOLERANCE,
                                             SINGULAR_TOLERANCE)
from occflownet.contract.metadata import METADATA_KEYS, REQUIRED_METADATA_KEYS
from occflownet.contract.tensors import CONTRACT_VERSION, INPUTS, NUM_CAMERAS, OUTPUTS, TensorSpec
from occflownet.files import atomic_path
from occflownet.occ3d import CLASS_NAMES, FREE, GRID

COMMAND = "python -m occflownet.contract.cpp_header"
HEADER_PATH = Path("embed/include/occflownet/contract_v1.hpp")     # relative to the repository root
MAX_RANK = max(spec.rank for spec in (*INPUTS, *OUTPUTS))


def _ident(name: str) -> str:
    """A contract name → its C++ constant: ``free_index`` → ``kFreeIndex``, ``cam2ego`` → ``kCam2ego``."""
    ident = "k" + "".join(part[:1].upper() + part[1:] for part in name.split("_"))
    if not re.fullmatch(r"k[A-Za-z0-9]+", ident):
        raise ValueError(f"contract name {name!r} makes no C++ identifier")
    return ident


def _string(text: str) -> str:
    """A C++ string literal (the contract's names are printable ASCII; anything else is refused)."""
    if not (text.isascii() and text.isprintable()):
        raise ValueError(f"contract name {text!r} is not printable ASCII")
    return json.dumps(text)


def _array(name: str, kind: str, items: Sequence[str]) -> str:
    """``inline constexpr auto name = std::array<kind, N>{{items}};`` on one line, or with the items on lines of
    their own when it would be longer than 118 characters."""
    head, tail = f"inline constexpr auto {name} = std::array<{kind}, {len(items)}>{{{{", "}};"
    if len(head + ", ".join(items) + tail) <= 118:
        return head + ", ".join(items) + tail
    lines, line = [], "   "
    for item in items:
        if len(line) > 3 and len(f"{line} {item},") > 118:
            lines.append(line)
            line = "   "
        line += f" {item},"
    return "\n".join([head, *lines, line.rstrip(","), tail])


def _tensor(spec: TensorSpec) -> str:
    dims = ", ".join("-1" if d is None else str(int(d)) for d in spec.shape)
    return (f"inline constexpr TensorSpec {_ident(spec.name)}{{{_string(spec.name)}, {_string(spec.dtype)}, "
            f"{spec.onnx_elem_type}, {spec.rank}, {{{{{dims}}}}}}};")


def _tensor_lines() -> list[str]:
    names = [_ident(s.name) for s in (*INPUTS, *OUTPUTS)]
    if len(set(names)) != len(names):
        raise ValueError(f"tensor names collide as C++ constants: {names}")
    return [
        "// One graph input or output: its name, element type (numpy name; ONNX TensorProto value, the same as",
        "// ONNXTensorElementDataType) and shape: the first `rank` entries of `dims`, -1 = a dynamic dimension.",
        "struct TensorSpec {",
        "    const char* name;",
        "    const char* dtype;",
        "    int element_type;",
        "    std::size_t rank;",
        "    std::array<std::int64_t, kMaxRank> dims;",
        "};",
        "",
        *(_tensor(spec) for spec in (*INPUTS, *OUTPUTS)),
        "",
        "// The inputs and outputs in graph order, and their names (as onnxruntime's Session::Run takes them).",
        _array("kInputs", "TensorSpec", [_ident(s.name) for s in INPUTS]),
        _array("kOutputs", "TensorSpec", [_ident(s.name) for s in OUTPUTS]),
        _array("kInputNames", "const char*", [_string(s.name) for s in INPUTS]),
        _array("kOutputNames", "const char*", [_string(s.name) for s in OUTPUTS]),
    ]


def _metadata_lines() -> list[str]:
    optional = [k for k in METADATA_KEYS if k not in REQUIRED_METADATA_KEYS]
    unknown = [k for k in REQUIRED_METADATA_KEYS if k not in METADATA_KEYS]
    if unknown:
        raise ValueError(f"REQUIRED_METADATA_KEYS {unknown} are not in METADATA_KEYS")
    return [
        "// The keys of metadata_props (every value JSON-encoded): those a consumer cannot do without, and the",
        "// optional ones every export also writes.",
        "namespace metadata {",
        *(f"inline constexpr const char* {_ident(key)} = {_string(key)};" for key in METADATA_KEYS),
        _array("kRequired", "const char*", [_ident(k) for k in REQUIRED_METADATA_KEYS]),
        _array("kOptional", "const char*", [_ident(k) for k in optional]),
        "}  // namespace metadata",
    ]


def render_header() -> str:
    """The text of ``embed/include/occflownet/contract_v1.hpp`` for the contract as this package defines it."""
    lines = [
        f"// Generated by `{COMMAND}`, do not edit: change occflownet/contract/ (or",
        "// occflownet/occ3d.py) and run the command again. tests/test_contract_cpp_header.py fails while this file",
        "// differs from what the command writes.",
        f"// ONNX contract {CONTRACT_VERSION} of occflownet model files as C++17 constants (docs/contracts.md).",
        "#pragma once",
        "",
        "#include <array>",
        "#include <cstddef>",
        "#include <cstdint>",
        "",
        "namespace occflownet::contract {",
        "",
        "// The contract's version: the value of the metadata key onnx_contract.",
        f"inline constexpr const char* kVersion = {_string(CONTRACT_VERSION)};",
        "// V: the cameras of every frame.",
        f"inline constexpr int kNumCameras = {NUM_CAMERAS};",
        "// [X, Y, Z] of the output grid.",
        f"inline constexpr std::array<int, 3> kGridShape{{{{{', '.join(map(str, GRID.shape))}}}}};",
        "// The entries of the metadata's `classes` (free space included) and the class id of free space.",
        f"inline constexpr int kNumClasses = {len(CLASS_NAMES)};",
        f"inline constexpr int kFreeIndex = {FREE};",
        "// The largest rank of a contract tensor.",
        f"inline constexpr std::size_t kMaxRank = {MAX_RANK};",
        "",
        *_tensor_lines(),
        "",
        *_metadata_lines(),
        "",
        "// Calibration checks and the intrinsics-rescaling rule (occflownet/contract/calibration.py): the relative",
        "// w/h difference allowed when rescaling intrinsics, the largest |R^T R - I| of a cam2ego rotation, and the",
        "// |det K| below which an intrinsic matrix is singular.",
        f"inline constexpr double kAspectTolerance = {float(ASPECT_TOLERANCE)!r};",
        f"inline constexpr double kOrthonormalTolerance = {float(ORTHONORMAL_TOLERANCE)!r};",
        f"inline constexpr double kSingularTolerance = {float(SINGULAR_TOLERANCE)!r};",
        "// Calibration JSON limits: its largest size in bytes, its deepest nesting of arrays and objects, the largest",
        "// width or height an image_size may state, and the magnitude below which a number (a double) rounds to a",
        "// finite float32 (every matrix entry must be below it).",
        f"inline constexpr std::size_t kMaxCalibrationBytes = {int(MAX_CALIBRATION_BYTES)};",
        f"inline constexpr int kMaxCalibrationDepth = {int(MAX_CALIBRATION_DEPTH)};",
        f"inline constexpr int kMaxImageSide = {int(MAX_IMAGE_SIDE)};",
        f"inline constexpr double kFloat32Limit = {float(FLOAT32_LIMIT)!r};",
        "",
        "}  // namespace occflownet::contract",
    ]
    return "\n".join(lines) + "\n"


def write_header(path: str | Path = HEADER_PATH) -> Path:
    """Write :func:`render_header` to ``path`` atomically → the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(render_header(), encoding="utf-8")
    return path


def header_is_current(path: str | Path = HEADER_PATH) -> bool:
    """Whether the file at ``path`` is exactly what :func:`render_header` gives now."""
    path = Path(path)
    return path.is_file() and path.read_text(encoding="utf-8") == render_header()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=COMMAND, description="write contract v1 as a C++ header for embed/")
    parser.add_argument("--out", type=Path, default=HEADER_PATH,
                        help=f"the header to write or check (default: {HEADER_PATH}, from the repository root)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if the header differs")
    args = parser.parse_args(argv)
    if args.out == HEADER_PATH and not Path("embed").is_dir():
        print(f"{COMMAND}: no embed/ here: run it from the repository root or give --out", file=sys.stderr)
        return 2
    if args.check:
        if header_is_current(args.out):
            print(f"{args.out} is current")
            return 0
        print(f"{args.out} differs from contract {CONTRACT_VERSION}: run `{COMMAND}`", file=sys.stderr)
        return 1
    print(f"wrote {write_header(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
