"""Files that appear whole or not at all: write to a temporary file in the destination's folder, then rename.

``os.replace`` within one folder (one file system) is atomic, so a reader sees the old file or the new one, never a
half-written one, and a run killed while writing leaves at most a hidden ``.<name>.*.tmp`` file behind.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path, fsync: bool = False):
    """Yield a temporary path beside ``path`` (same folder, created if needed); on a clean exit it replaces
    ``path``, on an exception it is removed. The caller writes the temporary path (keeping its suffix, so that
    libraries that look at the suffix, e.g. ``np.savez``, write what is asked). With ``fsync`` the written file is
    flushed to the disk before the rename (checkpoints: a power cut leaves the old file or the whole new one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + "".join(path.suffixes[-1:]), dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if fsync:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
