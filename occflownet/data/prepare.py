"""Prepare a nuScenes-format root for training: the sample index, the class counts and weights, the box flows.

Writes ``DATAROOT/occflownet/<version>/index.npz`` + ``index.json`` (``save_index``) and the flow records beside
them (``precompute_flow``). Re-running is idempotent: the index is rebuilt from the tables (same content) and the
class counts are reused while their fingerprint (:func:`class_stats_fingerprint`: the index arrays, the counted
split and the ray settings that decide which LiDAR points count) is unchanged.
"""
from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from occflownet.data.builder import build_index
from occflownet.data.class_weights import compute_class_stats
from occflownet.data.flow import precompute_flow
from occflownet.data.index import SampleIndex, index_dir, save_index
from occflownet.data.rays import RayBuilder, RayConfig
from occflownet.data.tables import DatasetError
from occflownet.options import check_fields, option


class UnknownSplit(DatasetError):
    """The split asked for the class counts is not defined by the root."""


@dataclass(frozen=True)
class PrepareConfig:
    """What :func:`prepare` does to a root; `occflownet prepare` derives its options from these fields
    (``occflownet/options.py``)."""

    version: str | None = option(None, "table directory, e.g. v1.0-mini (default: the only one under DATAROOT)")
    split: str | None = option(None, "split whose LiDAR points are counted for the class weights (default: 'train' "
                                     "when the root defines it, else 'all')")
    verify_files: bool = option(False, "check that every image, LiDAR, lidarseg and Occ3D file referenced exists")
    recount: bool = option(False, "recount classes even if the counts are current")
    flow_horizon: int = option(3, "box flows are precomputed for the frames t in [-FLOW_HORIZON, FLOW_HORIZON] "
                                  "(training's --horizon must not exceed it)", minimum=0)
    skip_class_counts: bool = option(False, "write the index only (e.g. a root without nuScenes-lidarseg)")

    def __post_init__(self):
        check_fields(self)


@dataclass
class PrepareResult:
    index: SampleIndex
    index_dir: Path                 # where index.npz / index.json were written
    flow_path: Path                 # the flow records
    counts_split: str | None        # the split whose classes were counted (None: counts skipped)
    counts_reused: bool             # the counts were current and taken from the previous index.json


def class_stats_fingerprint(index: SampleIndex, split: str, config: RayConfig) -> str:
    """sha256 hex of what the class counts depend on: every index array, the split's scenes, the ray settings."""
    digest = hashlib.sha256()
    for name in sorted(index.arrays):
        digest.update(name.encode() + index.arrays[name].tobytes())
    digest.update(json.dumps([split, index.splits[split], config.min_depth, config.ignored_raw_labels]).encode())
    return digest.hexdigest()


def counts_split(index: SampleIndex, split: str | None) -> str:
    """The split to count: ``split``, else 'train' when the root defines it, else 'all'; UnknownSplit if absent."""
    name = split or ("train" if "train" in index.splits else "all")
    if name not in index.splits:
        raise UnknownSplit(f"unknown split {name!r}; available: {', '.join(index.available_splits())}")
    return name


def prepare(dataroot, config: PrepareConfig = PrepareConfig(), *, progress: bool = False,
            on_index: Callable[[SampleIndex], None] | None = None, **changes) -> PrepareResult:
    """Index ``dataroot`` (``config.version``: its table folder, default the only one), count the classes of
    ``config.split`` (unless ``skip_class_counts``, or the counts are current and ``recount`` is False), write the
    index, then the box flows of t ∈ [−flow_horizon, flow_horizon]. ``changes``: fields of :class:`PrepareConfig`
    that replace those of ``config`` (``prepare(root, recount=True)``). ``on_index`` is called with the fresh
    index before the (slow) counting starts. Raises DatasetError (UnknownSplit for an unknown split) naming what is
    wrong."""
    config = replace(config, **changes)
    index = build_index(dataroot, config.version, verify_files=config.verify_files)
    if on_index is not None:
        on_index(index)
    name, reused = None, False
    if not config.skip_class_counts:
        name = counts_split(index, config.split)
        rays = RayConfig()
        fingerprint = class_stats_fingerprint(index, name, rays)
        previous = _previous_meta(index_dir(dataroot, index.version))
        reused = (not config.recount and previous.get("class_stats_fingerprint") == fingerprint
                  and "class_stats" in previous)
        if reused:
            index.meta["class_stats"] = previous["class_stats"]
        else:
            builder = RayBuilder(index, dataroot, rays, cache_size=0)
            index.meta["class_stats"] = compute_class_stats(builder, name, progress=progress).to_dict()
        index.meta["class_stats_fingerprint"] = fingerprint
    out = save_index(index, dataroot)
    flow = precompute_flow(index, dataroot, horizon=config.flow_horizon, progress=progress)
    return PrepareResult(index, out, flow, name, reused)


def _previous_meta(folder: Path) -> dict:
    try:
        return json.loads((folder / "index.json").read_text())
    except (OSError, ValueError):
        return {}
