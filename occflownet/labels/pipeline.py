"""``label_root``: Occ3D labels for every keyframe of a nuScenes-format root, by scene, in parallel and in shards.

Writes ``<out>/gts/<scene name>/<sample token>/labels.npz`` (``out`` defaults to the dataroot) and
``<out>/gts/labels.json`` (the settings and the package version). Each file appears whole or not at all; a rerun
skips the keyframes whose file exists (``overwrite`` redoes them) and refuses to mix settings: labels made with
other settings, or a ``gts/`` the pipeline did not write (e.g. downloaded Occ3D labels), are an error unless
``overwrite``. Scenes are labelled in ``workers`` processes; ``shard="i/n"`` takes the scenes whose position in name
order is i mod n, so that n machines can split a dataset. What a call reads and writes is a :class:`LabelRun`; how
the labels are made, a :class:`~occflownet.labels.config.LabelConfig`.
"""
from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from occflownet import __version__
from occflownet.data.builder import index_from_tables
from occflownet.data.index import SampleIndex
from occflownet.data.sweeps import LidarSweep, scene_sweeps
from occflownet.data.tables import DatasetError, load_tables
from occflownet.files import atomic_path
from occflownet.labels.accumulate import load_scene_cloud
from occflownet.labels.config import LabelConfig
from occflownet.labels.keyframe import label_keyframe, window_sweeps
from occflownet.labels.npz import write_labels_npz
from occflownet.options import check_fields, option
from occflownet.worker_processes import spawn_context

SETTINGS_FILE = "labels.json"


class LabelError(DatasetError):
    """The root cannot be labelled as asked (no lidarseg without geometry-only, settings that differ, ...)."""


@dataclass(frozen=True)
class LabelRun:
    """Which root version one :func:`label_root` call reads, where it writes, which scenes it takes and how it
    spreads them over processes: how the labels are made is :class:`LabelConfig`. `occflownet labels` derives its
    options from these fields and LabelConfig's (``occflownet/options.py``)."""

    version: str | None = option(None, "table directory (default: the only one under DATAROOT)")
    out: str | None = option(None, "write OUT/gts/... instead of DATAROOT/gts/...")
    workers: int = option(1, "scenes labelled in parallel processes", minimum=1)
    shard: str = option("0/1", "I/N: label the scenes whose position in name order is I mod N (0/1: all)")
    overwrite: bool = option(False, "redo existing labels (also those made with other settings or by another tool)")

    def __post_init__(self):
        check_fields(self)
        shard_pair(self.shard)


def shard_pair(shard: str) -> tuple[int, int]:
    """``shard`` "I/N" as (I, N); ValueError naming it unless 0 <= I < N."""
    try:
        i, n = (int(v) for v in str(shard).split("/"))
    except ValueError:
        raise ValueError(f"shard must be I/N, got {shard!r}") from None
    if not 0 <= i < n:
        raise ValueError(f"shard must be I/N with 0 <= I < N, got {shard!r}")
    return i, n


@dataclass
class LabelReport:
    """What one ``label_root`` call did."""

    out: Path                                   # the gts folder
    scenes: list[str]                           # the scenes of this shard
    written: int = 0                            # keyframe files written
    skipped: int = 0                            # keyframe files that existed
    seconds: float = 0.0
    keyframes: list[dict] = field(default_factory=list)   # per written keyframe: scene, token, seconds, stats
    warnings: list[str] = field(default_factory=list)


def label_root(dataroot, config: LabelConfig = LabelConfig(), run: LabelRun = LabelRun(), *,
               progress: bool = True, **changes) -> LabelReport:
    """Label every keyframe of the scenes of ``run.shard`` (see the module docstring) as ``config`` says.
    ``changes``: fields of :class:`LabelRun` that replace those of ``run`` (``label_root(root, out=o, workers=2)``).
    DatasetError naming the file or record at fault on bad input, LabelError when the root cannot be labelled as
    asked, ValueError for a bad ``run``."""
    start = time.perf_counter()
    run = replace(run, **changes)
    tables = load_tables(dataroot, run.version)
    index = index_from_tables(tables, occupancy=False)
    _require_lidarseg(index, config)
    gts = Path(run.out if run.out is not None else dataroot) / "gts"
    _check_settings(gts, config, run.overwrite)
    names = _shard(index.scene_names, shard_pair(run.shard))
    report = LabelReport(gts, names)
    sweeps = scene_sweeps(tables, index)
    jobs = []
    for name in names:
        positions = _pending(index, name, gts, run.overwrite)
        report.skipped += _scene_size(index, name) - len(positions)
        if positions:
            jobs.append((name, positions))
    bar = _bar(sum(len(p) for _, p in jobs), progress)
    for scene_report in _run(jobs, index, sweeps, tables.dataroot, gts, config, run.workers):
        report.written += len(scene_report["keyframes"])
        report.keyframes += scene_report["keyframes"]
        report.warnings += scene_report["warnings"]
        bar.update(len(scene_report["keyframes"]))
    bar.close()
    report.seconds = time.perf_counter() - start
    return report


def _require_lidarseg(index: SampleIndex, config: LabelConfig) -> None:
    if config.geometry_only:
        return
    missing = [index.tokens[p] for p, path in enumerate(index.arrays["lidarseg_path"]) if not path]
    if missing:
        raise LabelError(f"{len(missing)} of {len(index)} keyframes have no lidarseg labels (e.g. sample "
                         f"{missing[0]}): classes come from nuScenes-lidarseg (lidarseg.json and lidarseg/ in the "
                         f"dataroot); without it, run with --geometry-only for occupancy and masks without classes")


def _check_settings(gts: Path, config: LabelConfig, overwrite: bool) -> None:
    """Write ``gts/labels.json``, or refuse when ``gts`` holds labels made otherwise (unless ``overwrite``)."""
    path = gts / SETTINGS_FILE
    wanted = {"format": 1, "config": config.to_dict()}
    if not overwrite:
        if path.is_file():
            previous = json.loads(path.read_text())
            if {k: previous.get(k) for k in wanted} != wanted:
                raise LabelError(f"{path}: the labels in {gts} were made with other settings "
                                 f"({json.dumps(previous.get('config'))}); pass --overwrite to redo them, or --out "
                                 f"to write elsewhere")
        elif gts.is_dir() and any(gts.iterdir()):
            raise LabelError(f"{gts} holds labels that occflownet labels did not write (no {SETTINGS_FILE}); pass "
                             f"--out to write elsewhere, or --overwrite to replace them")
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**wanted, "package_version": __version__}, indent=1))


def _shard(scene_names: list[str], shard: tuple[int, int]) -> list[str]:
    i, n = shard
    return [name for j, name in enumerate(sorted(scene_names)) if j % n == i]


def _scene_positions(index: SampleIndex, name: str) -> range:
    s = index.scene_names.index(name)
    return range(int(index.arrays["scene_start"][s]), int(index.arrays["scene_start"][s + 1]))


def _scene_size(index: SampleIndex, name: str) -> int:
    return len(_scene_positions(index, name))


def _pending(index: SampleIndex, name: str, gts: Path, overwrite: bool) -> list[int]:
    return [p for p in _scene_positions(index, name)
            if overwrite or not (gts / name / index.tokens[p] / "labels.npz").is_file()]


def _bar(total: int, progress: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc="labels", unit="kf", file=sys.stderr, disable=not progress)


def _run(jobs, index, sweeps, dataroot, gts, config, workers):
    """Yield each scene's report (in ``jobs`` order with one worker, as they finish with several)."""
    if workers <= 1 or len(jobs) <= 1:
        for name, positions in jobs:
            yield label_scene(dataroot, index, sweeps[name], name, positions, gts, config)
        return
    threads = max(1, (os.cpu_count() or 1) // workers)
    with ProcessPoolExecutor(max_workers=workers, mp_context=spawn_context(), initializer=_init_worker,
                             initargs=(threads,)) as pool:
        futures = [pool.submit(label_scene, dataroot, index, sweeps[name], name, positions, gts, config)
                   for name, positions in jobs]
        for f in futures:
            yield f.result()


def _init_worker(threads: int) -> None:
    """Each worker process uses its share of the cores for the compiled walks."""
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except ImportError:
        pass


def label_scene(dataroot, index: SampleIndex, sweeps: list[LidarSweep], name: str, positions: list[int], gts: Path,
                config: LabelConfig) -> dict:
    """Label the keyframes ``positions`` of scene ``name`` and write their files → {"keyframes": [...],
    "warnings": [...]}."""
    scene = _scene_positions(index, name)
    warnings = []
    if int(index.arrays["box_start"][scene.stop]) == int(index.arrays["box_start"][scene.start]):
        warnings.append(f"scene {name} has no annotated boxes: all of its points are treated as static")
    cloud = load_scene_cloud(dataroot, index, sweeps, scene.start, scene.stop, config)
    times = index.arrays["lidar_timestamp"][scene.start:scene.stop]
    done = []
    for p in positions:
        t0 = time.perf_counter()
        sample = index[p]
        use = window_sweeps(cloud, times, p - scene.start, config.window)
        labels = label_keyframe(cloud, sample, use, config)
        extra = {"geometry_only": np.uint8(1)} if config.geometry_only else {}
        write_labels_npz(gts / name / sample.token / "labels.npz", labels.semantics, labels.mask_lidar,
                         labels.mask_camera, **extra)
        done.append({"scene": name, "token": sample.token, "seconds": time.perf_counter() - t0, **labels.stats})
    return {"keyframes": done, "warnings": warnings,
            "unlabelled_sweep_points": cloud.unlabelled_sweep_points, "points": len(cloud)}
