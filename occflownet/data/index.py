"""The sample index: every keyframe of a nuScenes-format root, stored column-wise, saved once by ``prepare``.

On disk (``DATAROOT/occflownet/<version>/``):
- ``index.npz``: uncompressed numpy arrays, no pickles (layout: ``ARRAY_LAYOUT`` below);
- ``index.json``: metadata: ``format_version``, ``package_version``, ``version``, sample/scene counts, the splits
  (name → scene names), the byte sizes of the tables it was built from (a changed root is detected on load), and,
  after ``prepare``, ``class_stats`` (per-class LiDAR point counts and loss weights, see ``class_weights``).

``index[i]`` builds a :class:`~occflownet.data.records.SampleRecord` on demand. Samples of a scene are contiguous
and in time order, so temporal neighbours are positions ``i + t`` inside the scene's range.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occflownet import __version__
from occflownet.files import atomic_path
from occflownet.occ3d import CAMERAS
from occflownet.data.records import Boxes, CameraRecord, LidarRecord, SampleRecord
from occflownet.data.tables import OPTIONAL_TABLES, REQUIRED_TABLES, DatasetError, resolve_version

FORMAT_VERSION = 1
INDEX_DIRNAME = "occflownet"

# name: meaning (S = samples, Sc = scenes, B = boxes of all samples, I = instances, C = categories).
# Strings are stored as bytes (numpy "S"); an empty string means "none".
ARRAY_LAYOUT = {
    "scene_name": "bytes [Sc]", "scene_token": "bytes [Sc]", "scene_start": "int64 [Sc+1] first sample position",
    "sample_token": "bytes [S]", "sample_timestamp": "int64 [S] µs", "sample_scene": "int64 [S] scene id",
    "cam_token": "bytes [S, 6]", "cam_path": "bytes [S, 6]", "cam_intrinsic": "float64 [S, 6, 3, 3]",
    "cam_sensor2ego": "float64 [S, 6, 4, 4]", "cam_ego2global": "float64 [S, 6, 4, 4] at camera timestamp",
    "cam_timestamp": "int64 [S, 6]", "cam_size": "int64 [S, 6, 2] (width, height)",
    "lidar_token": "bytes [S]", "lidar_path": "bytes [S]", "lidar_sensor2ego": "float64 [S, 4, 4]",
    "lidar_ego2global": "float64 [S, 4, 4] at LiDAR timestamp", "lidar_timestamp": "int64 [S]",
    "lidarseg_path": "bytes [S] ('' = none)", "occupancy_path": "bytes [S] ('' = none)",
    "box_start": "int64 [S+1] first box of each sample", "box_instance": "int64 [B] into instance_token",
    "instance_token": "bytes [I]", "box_category": "int64 [B] into category_name", "category_name": "bytes [C]",
    "box_label": "uint8 [B] Occ3D class", "box_translation": "float64 [B, 3] global",
    "box_size": "float64 [B, 3] (w, l, h)", "box_rotation": "float64 [B, 4] (w, x, y, z) global",
}

MINI_SPLITS = {
    "mini_train": ["scene-0061", "scene-0553", "scene-0655", "scene-0757", "scene-0796", "scene-1077",
                   "scene-1094", "scene-1100"],
    "mini_val": ["scene-0103", "scene-0916"],
}


def _s(value: bytes) -> str:
    return value.decode("utf-8")


def _opt(value: bytes) -> str | None:
    return value.decode("utf-8") or None


class SampleIndex:
    """All keyframes of one version of a root. ``len(index)`` samples; ``index[i]`` → SampleRecord."""

    def __init__(self, version: str, arrays: dict[str, np.ndarray], splits: dict[str, list[str]],
                 meta: dict | None = None):
        missing = sorted(set(ARRAY_LAYOUT) - set(arrays))
        if missing:
            raise DatasetError(f"sample index arrays lack {', '.join(missing)}")
        self.version = version
        self.arrays = arrays
        self.splits = splits
        self.meta = dict(meta or {})
        self.tokens: list[str] = [_s(t) for t in arrays["sample_token"]]
        self._position = {t: i for i, t in enumerate(self.tokens)}
        self.scene_names: list[str] = [_s(n) for n in arrays["scene_name"]]
        for split, names in splits.items():
            unknown = sorted(set(names) - set(self.scene_names))
            if unknown:
                raise DatasetError(f"split '{split}' names scenes this root does not have: {', '.join(unknown)}")

    def __len__(self) -> int:
        return len(self.tokens)

    def position_of(self, token: str) -> int:
        """Position of a sample token (KeyError naming it when unknown)."""
        try:
            return self._position[token]
        except KeyError:
            raise KeyError(f"sample token {token!r} is not in the index of {self.version}") from None

    def scene_range(self, position: int) -> tuple[int, int]:
        """[start, stop) positions of the scene that holds sample ``position``."""
        scene = int(self.arrays["sample_scene"][position])
        return int(self.arrays["scene_start"][scene]), int(self.arrays["scene_start"][scene + 1])

    def neighbours(self, position: int, horizon: int) -> list[tuple[int, int]]:
        """[(t, position of keyframe i+t)] for t in [-horizon, horizon] inside the same scene, t ascending.

        At a scene's edge the list is shorter: frames are never duplicated or borrowed from another scene."""
        start, stop = self.scene_range(position)
        return [(t, position + t) for t in range(-horizon, horizon + 1) if start <= position + t < stop]

    def available_splits(self) -> list[str]:
        return sorted(self.splits)

    def split_positions(self, split: str) -> np.ndarray:
        """int64 positions of the samples of ``split`` (scene order, time order within a scene)."""
        if split not in self.splits:
            raise KeyError(f"unknown split {split!r} for {self.version}; available: {', '.join(self.available_splits())}")
        wanted = set(self.splits[split])
        scenes = [i for i, n in enumerate(self.scene_names) if n in wanted]
        starts = self.arrays["scene_start"]
        parts = [np.arange(starts[s], starts[s + 1]) for s in scenes]
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, dtype=np.int64)

    @property
    def class_stats(self):
        """The ClassStats written by ``prepare`` (per-class counts and loss weights), or None."""
        from occflownet.data.class_weights import ClassStats
        stats = self.meta.get("class_stats")
        return None if stats is None else ClassStats.from_dict(stats)

    def boxes(self, position: int) -> Boxes:
        a = self.arrays
        lo, hi = int(a["box_start"][position]), int(a["box_start"][position + 1])
        return Boxes(
            instance_tokens=np.array([_s(t) for t in a["instance_token"][a["box_instance"][lo:hi]]], dtype=str),
            category_names=np.array([_s(t) for t in a["category_name"][a["box_category"][lo:hi]]], dtype=str),
            labels=a["box_label"][lo:hi], translations=a["box_translation"][lo:hi], sizes=a["box_size"][lo:hi],
            rotations=a["box_rotation"][lo:hi],
        )

    def __getitem__(self, position: int) -> SampleRecord:
        if not -len(self) <= position < len(self):
            raise IndexError(f"sample position {position} out of range for {len(self)} samples")
        i = int(position) % len(self)
        a = self.arrays
        cams = tuple(
            CameraRecord(name=name, path=_s(a["cam_path"][i, c]), intrinsic=a["cam_intrinsic"][i, c],
                         sensor2ego=a["cam_sensor2ego"][i, c], ego2global=a["cam_ego2global"][i, c],
                         timestamp=int(a["cam_timestamp"][i, c]), width=int(a["cam_size"][i, c, 0]),
                         height=int(a["cam_size"][i, c, 1]), token=_s(a["cam_token"][i, c]))
            for c, name in enumerate(CAMERAS))
        lidar = LidarRecord(path=_s(a["lidar_path"][i]), sensor2ego=a["lidar_sensor2ego"][i],
                            ego2global=a["lidar_ego2global"][i], timestamp=int(a["lidar_timestamp"][i]),
                            token=_s(a["lidar_token"][i]))
        start, stop = self.scene_range(i)
        scene = int(a["sample_scene"][i])
        return SampleRecord(
            position=i, token=self.tokens[i], scene_name=self.scene_names[scene],
            scene_token=_s(a["scene_token"][scene]), timestamp=int(a["sample_timestamp"][i]),
            index_in_scene=i - start, scene_sample_tokens=tuple(self.tokens[start:stop]), cameras=cams,
            lidar=lidar, lidarseg_path=_opt(a["lidarseg_path"][i]), occupancy_path=_opt(a["occupancy_path"][i]),
            boxes=self.boxes(i),
        )

    def missing_files(self, dataroot) -> list[str]:
        """Paths (relative to ``dataroot``) referenced by the index that do not exist as files."""
        a, root = self.arrays, Path(dataroot)
        paths = [*a["cam_path"].ravel(), *a["lidar_path"], *a["lidarseg_path"], *a["occupancy_path"]]
        return [_s(p) for p in paths if p and not (root / _s(p)).is_file()]


# ---------------------------------------------------------------------------------------------- save / load
def index_dir(dataroot, version: str) -> Path:
    """``DATAROOT/occflownet/<version>``: where ``prepare`` writes the index of that version."""
    return Path(dataroot) / INDEX_DIRNAME / version


def save_index(index: SampleIndex, dataroot) -> Path:
    """Write ``index.npz`` and ``index.json`` (atomically, each) under ``index_dir``; returns that directory."""
    out = index_dir(dataroot, index.version)
    with atomic_path(out / "index.npz") as tmp:
        np.savez(tmp, **index.arrays)
    meta = {**index.meta, "format_version": FORMAT_VERSION, "package_version": __version__,
            "version": index.version, "num_samples": len(index), "num_scenes": len(index.scene_names),
            "splits": index.splits}
    with atomic_path(out / "index.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=1) + "\n")
    return out


def load_index(dataroot, version: str | None = None, check_tables: bool = True) -> SampleIndex:
    """Read the index ``prepare`` wrote for ``DATAROOT/<version>`` (version None: the only one there).

    Errors clearly when it is missing, was written by another format version, or (``check_tables``) when the
    tables changed size since it was written (a regenerated root): re-run ``occflownet prepare`` then."""
    dataroot = Path(dataroot)
    if version is None:
        written = sorted(p.parent.name for p in (dataroot / INDEX_DIRNAME).glob("*/index.json"))
        version = written[0] if len(written) == 1 else resolve_version(dataroot, None)
    folder = index_dir(dataroot, version)
    command = f"`occflownet prepare --dataroot {dataroot} --version {version}`"
    if not (folder / "index.json").is_file() or not (folder / "index.npz").is_file():
        raise DatasetError(f"no sample index at {folder}: run {command} first")
    meta = json.loads((folder / "index.json").read_text())
    if meta.get("format_version") != FORMAT_VERSION:
        raise DatasetError(f"{folder / 'index.json'}: index format {meta.get('format_version')}, this package "
                           f"reads format {FORMAT_VERSION}: re-run {command}")
    if check_tables:
        sizes = meta.get("table_sizes", {})
        for name in (*REQUIRED_TABLES, *OPTIONAL_TABLES):
            path = dataroot / version / f"{name}.json"
            size = path.stat().st_size if path.is_file() else None
            if size != sizes.get(name):
                raise DatasetError(f"{path} changed since the index was written: re-run {command}")
    with np.load(folder / "index.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    splits = meta.pop("splits")
    return SampleIndex(version, arrays, splits, meta)
