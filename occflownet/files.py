"""Files that appear whole or not at all: write to a temporary file in the destination's folder, then rename.

``os.replace`` within one folder (one file system) is atomic, so a reader sees the old file or the new one, never a
half-written one, and a run killed while writing leaves at most a hidden ``.<name>.*.tmp`` file behind.

The temporary file is created as ``open(path, "w")`` creates a new file: mode 0o666, from which the kernel takes
away the process's umask (or applies the folder's default ACL), so the result is 0644 under umask 022 and 0600 under
077. Nothing reads or sets the umask (``os.umask`` is process-wide, and setting it to read it races with other
threads); ``tempfile.mkstemp`` is not used because it creates 0600 whatever the umask.
"""
from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path

_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)


def _new_file_beside(path: Path) -> Path:
    """Create an empty file ``.<name>.<random>.tmp<suffix>`` in ``path``'s folder, mode 0o666 less the umask;
    ``O_EXCL``: never an existing file (another writer's temporary or a planted link), a new name instead."""
    suffix = ".tmp" + "".join(path.suffixes[-1:])
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}{suffix}"
        try:
            os.close(os.open(tmp, _CREATE, 0o666))
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"no free temporary name beside {path} after 100 tries")


@contextmanager
def atomic_path(path, fsync: bool = False):
    """Yield a temporary path beside ``path`` (same folder, created if needed); on a clean exit it replaces
    ``path``, on an exception it is removed. The caller writes the temporary path (keeping its suffix, so that
    libraries that look at the suffix, e.g. ``np.savez``, write what is asked). The file gets the mode ``open()``
    gives a new file (module docstring), also when it replaces an older one. With ``fsync`` the written file is
    flushed to the disk before the rename (checkpoints: a power cut leaves the old file or the whole new one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_file_beside(path)
    try:
        yield tmp
        if fsync:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
