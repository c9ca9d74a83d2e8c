"""Read the JSON tables of a nuScenes-format root directly (no nuscenes-devkit).

A root looks like ``DATAROOT/<version>/{scene,sample,sample_data,...}.json`` with the sensor files under
``DATAROOT/samples``/``sweeps`` and, optionally, ``DATAROOT/<version>/lidarseg.json`` (nuScenes-lidarseg) and
``DATAROOT/gts/<scene name>/<sample token>/labels.npz`` (Occ3D). Every problem is reported as a
:class:`DatasetError` that names the table, the record token and the field (or the file) at fault.
"""
from __future__ import annotations

import json
from pathlib import Path

# The tables the sample index is built from. The devkit needs more (log, map, attribute, visibility); we do not.
REQUIRED_TABLES: tuple[str, ...] = (
    "scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor", "sample_annotation", "instance",
    "category",
)
OPTIONAL_TABLES: tuple[str, ...] = ("lidarseg",)


class DatasetError(ValueError):
    """A nuScenes-format root is missing a table, file or field, or holds inconsistent records."""


def find_versions(dataroot: Path) -> list[str]:
    """Names of the sub-directories of ``dataroot`` that hold a ``sample.json`` (e.g. ``v1.0-mini``), sorted."""
    dataroot = Path(dataroot)
    if not dataroot.is_dir():
        return []
    return sorted(p.name for p in dataroot.iterdir() if (p / "sample.json").is_file())


def resolve_version(dataroot: Path, version: str | None) -> str:
    """``version`` itself, or, when None, the only table directory under ``dataroot`` (error if 0 or several)."""
    dataroot = Path(dataroot)
    if not dataroot.is_dir():
        raise DatasetError(f"dataroot {dataroot} does not exist or is not a directory")
    versions = find_versions(dataroot)
    if version is None:
        if len(versions) != 1:
            found = ", ".join(versions) if versions else "none"
            raise DatasetError(f"{dataroot}: cannot choose a version automatically (table directories found: "
                               f"{found}); pass --version")
        return versions[0]
    if not (dataroot / version).is_dir():
        found = ", ".join(versions) if versions else "none"
        raise DatasetError(f"{dataroot / version}: version directory not found (table directories in {dataroot}: "
                           f"{found})")
    return version


def read_table(dataroot: Path, version: str, name: str) -> list[dict]:
    """One table ``DATAROOT/<version>/<name>.json`` as a list of records."""
    path = Path(dataroot) / version / f"{name}.json"
    if not path.is_file():
        raise DatasetError(f"{path}: nuScenes table '{name}' is missing")
    try:
        with open(path, encoding="utf-8") as f:
            records = json.load(f)
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise DatasetError(f"{path}: table '{name}' must be a JSON list of objects")
    return records


def field(record: dict, table: str, name: str):
    """``record[name]``, or a :class:`DatasetError` naming the table, the record's token and the field."""
    try:
        return record[name]
    except KeyError:
        token = record.get("token", "<no token>")
        raise DatasetError(f"table '{table}': record {token} lacks field '{name}'") from None


class Tables:
    """The tables of one nuScenes-format root, with token lookups that fail loudly.

    ``tables.records[name]`` is the raw list; ``tables.get(name, token, referrer)`` returns one record or raises a
    :class:`DatasetError` naming the referring record when the token does not exist.
    """

    def __init__(self, dataroot: Path, version: str, records: dict[str, list[dict]]):
        self.dataroot = Path(dataroot)
        self.version = version
        self.records = records
        self._by_token: dict[str, dict[str, dict]] = {}

    def has(self, name: str) -> bool:
        return name in self.records

    def by_token(self, name: str) -> dict[str, dict]:
        """token → record for table ``name`` (built once; duplicate tokens are an error)."""
        if name not in self._by_token:
            table = {}
            for record in self.records[name]:
                token = field(record, name, "token")
                if token in table:
                    raise DatasetError(f"table '{name}': token {token} occurs more than once")
                table[token] = record
            self._by_token[name] = table
        return self._by_token[name]

    def get(self, name: str, token: str, referrer: str) -> dict:
        """The record ``token`` of table ``name``; ``referrer`` says who refers to it (for the error message)."""
        try:
            return self.by_token(name)[token]
        except KeyError:
            raise DatasetError(f"{referrer} refers to {name} token {token!r}, which table '{name}' lacks") from None

    def table_sizes(self) -> dict[str, int]:
        """Byte size of every table file read: a cheap fingerprint to detect a regenerated root."""
        out = {}
        for name in self.records:
            out[name] = (self.dataroot / self.version / f"{name}.json").stat().st_size
        return out


def load_tables(dataroot, version: str | None = None) -> Tables:
    """Read the required tables (and ``lidarseg.json`` when present) of ``DATAROOT/<version>``."""
    dataroot = Path(dataroot)
    version = resolve_version(dataroot, version)
    records = {name: read_table(dataroot, version, name) for name in REQUIRED_TABLES}
    for name in OPTIONAL_TABLES:
        if (dataroot / version / f"{name}.json").is_file():
            records[name] = read_table(dataroot, version, name)
    return Tables(dataroot, version, records)
