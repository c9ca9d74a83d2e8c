"""What `occflownet export` writes beside the fp32 model: the reduced-precision variants
(:mod:`occflownet.export.variants`) and the int8 weights' range. Neither torch nor onnx is imported here, so that
the command line reads these fields when it starts."""
from __future__ import annotations

from dataclasses import dataclass

from occflownet.choices import INT8_RANGES
from occflownet.options import check_fields, option


@dataclass(frozen=True)
class ExportConfig:
    """The export's variants; `occflownet export` derives its options from these fields
    (``occflownet/options.py``)."""

    fp16: bool = option(False, "also write <out>.fp16.onnx (float16 weights/compute)")
    int8: bool = option(False, "also write <out>.int8.onnx (static QDQ quantisation, calibrated on the first "
                               "--parity-frame, else on synthetic samples)")
    int8_range: str = option("reduced", "int8 weights: 7-bit, exact on every x86 CPU (reduced) or 8-bit, for CPUs "
                                        "with VNNI or AMX (full; on AVX2-only CPUs onnxruntime's kernels may "
                                        "saturate)", choices=INT8_RANGES)

    def __post_init__(self):
        check_fields(self)
