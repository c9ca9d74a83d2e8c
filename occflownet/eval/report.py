"""Reporting of evaluation results: JSON-ready dicts (stdout) and a readable per-class table (stderr).

Results are the dicts of ``OccupancyMetric.compute()`` (``"metric": "occ3d_miou"``) and
``RayIoUMetric.compute()`` (``"metric": "rayiou"``), or a dict holding several of them under any keys (other
entries are ignored by the table and passed through by the JSON). IoUs in the dicts are fractions in [0, 1];
the table prints percentages.
"""
from __future__ import annotations

import json
import math

import numpy as np

from occflownet.occ3d import CLASS_NAMES, DYNAMIC_CLASSES, NUM_CLASSES


def to_json_ready(obj):
    """Recursively convert a result to plain JSON types: numpy scalars/arrays → Python numbers/lists, tuples →
    lists, non-finite floats (NaN = class absent, inf) → None. Dict keys become strings."""
    if isinstance(obj, dict):
        return {str(k): to_json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json_ready(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def dumps_json(result, indent: int | None = 2) -> str:
    """The result as strict JSON text (NaN → null; never emits the non-standard ``NaN`` token)."""
    return json.dumps(to_json_ready(result), indent=indent, allow_nan=False)


def _metrics_in(result: dict) -> list[dict]:
    if not isinstance(result, dict):
        raise TypeError(f"format_table expects a result dict, got {type(result).__name__}")
    if result.get("metric") in ("occ3d_miou", "rayiou"):
        return [result]
    found = [v for v in result.values() if isinstance(v, dict) and v.get("metric") in ("occ3d_miou", "rayiou")]
    if not found:
        raise ValueError("format_table: no 'occ3d_miou' or 'rayiou' result in the dict "
                         f"(keys: {sorted(map(str, result))})")
    return found


def _pct(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{100.0 * float(value):.2f}"


def _ratio(value) -> str:
    return "-" if value is None else f"{float(value):.2f}"


def format_table(result: dict) -> str:
    """A per-class table of one or several results (see the module doc), values in percent.

    Columns: Occ3D IoU with the camera mask and over all voxels, RayIoU at each distance threshold. Rows: the
    17 classes (``*`` marks the paper's dynamic classes), then the means (mIoU / RayIoU@θ), the static and
    dynamic mIoU, the occupied-vs-free IoU, and a closing line with RayIoU and sample counts.
    """
    columns: list[tuple[str, list[str], dict[str, str]]] = []  # (header, per-class cells, summary cells)
    footer: list[str] = []
    for res in _metrics_in(result):
        if res["metric"] == "occ3d_miou":
            for key, header in (("camera_mask", "IoU cam"), ("all_voxels", "IoU all")):
                part = res.get(key)
                if part is None:
                    continue
                cells = [_pct(part["iou_per_class"].get(name)) for name in CLASS_NAMES[:NUM_CLASSES]]
                summary = {"mean": _pct(part["miou"]), "static": _pct(part["miou_static"]),
                           "dynamic": _pct(part["miou_dynamic"]), "geometry": _pct(part["geometry_iou"])}
                columns.append((header, cells, summary))
            footer.append(f"Occ3D mIoU: {_pct((res.get('camera_mask') or res['all_voxels'])['miou'])} "
                          f"({'camera mask' if res.get('camera_mask') else 'all voxels'}), "
                          f"{res['samples']} samples")
        else:
            for j, threshold in enumerate(res["thresholds_m"]):
                label = f"{threshold:g}"
                cells = [_pct(res["iou_per_class"][name][j]) for name in CLASS_NAMES[:NUM_CLASSES]]
                columns.append((f"Ray@{label}m", cells, {"mean": _pct(res[f"rayiou@{label}"])}))
            footer.append(f"RayIoU: {_pct(res['rayiou'])} (mean over {len(res['thresholds_m'])} thresholds × "
                          f"classes), {res['samples']} samples, {res['rays_with_gt_hit']} of "
                          f"{res['rays_cast']} rays with a ground-truth hit")

    name_width = max(len(n) for n in CLASS_NAMES) + 2
    widths = [max(len(header), 7) for header, _, _ in columns]
    head = "class".ljust(name_width) + "".join(f"  {h:>{w}}" for (h, _, _), w in zip(columns, widths))
    rule = "-" * len(head)
    lines = [head, rule]
    for c, name in enumerate(CLASS_NAMES[:NUM_CLASSES]):
        label = name + (" *" if c in DYNAMIC_CLASSES else "")
        lines.append(label.ljust(name_width) + "".join(f"  {col[1][c]:>{w}}" for col, w in zip(columns, widths)))
    lines.append(rule)
    for key, label in (("mean", "mean"), ("static", "static mean"), ("dynamic", "dynamic mean"),
                       ("geometry", "occupied IoU")):
        if any(key in col[2] for col in columns):
            lines.append((label.ljust(name_width)
                          + "".join(f"  {col[2].get(key, ''):>{w}}" for col, w in zip(columns, widths))).rstrip())
    lines.append(rule)
    lines.extend(footer)
    fog = result.get("fog") if isinstance(result, dict) else None
    if fog:
        cam, crossed, never = fog["camera_mask"], fog["crossed"], fog["never_crossed"]
        lines.append(f"fog (camera mask): {_pct(cam['predicted_fraction'])} % of voxels predicted occupied vs "
                     f"{_pct(cam['labelled_fraction'])} % labelled (x{_ratio(cam['fog_factor'])}); crossed by "
                     f"training rays ({_pct(fog['crossed_fraction'])} %): x{_ratio(crossed['fog_factor'])}, "
                     f"never crossed: x{_ratio(never['fog_factor'])}, {never['false_positive']} false positives")
    lines.append("values in %; * dynamic class (paper Table 2); '-' class absent from prediction and ground "
                 "truth, skipped by the means")
    return "\n".join(lines)
