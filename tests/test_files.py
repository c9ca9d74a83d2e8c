"""Files written through ``occflownet.files.atomic_path`` appear whole or not at all, with the mode ``open()`` gives a
new file: 0o666 less the process's umask (0644 under umask 022, 0600 under 077), for every writer of the package."""
from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from occflownet.files import atomic_path

# umask -> the mode open() gives a new file (0o666 & ~umask): the known answers.
MODES = {0o022: 0o644, 0o077: 0o600, 0o002: 0o664}


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture(params=sorted(MODES), ids=lambda u: f"umask{u:03o}")
def umask(request):
    """Run the test under this umask (process-wide; restored after it). pytest runs tests in one thread."""
    previous = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(previous)


def test_atomic_path_gives_the_mode_open_gives(tmp_path, umask):
    with open(tmp_path / "by-open.txt", "w") as f:
        f.write("x")
    with atomic_path(tmp_path / "sub" / "atomic.txt") as tmp:
        assert mode(tmp) == MODES[umask]               # also while it is written
        tmp.write_text("x")
    assert mode(tmp_path / "by-open.txt") == MODES[umask]
    assert mode(tmp_path / "sub" / "atomic.txt") == MODES[umask]


def test_a_replaced_file_gets_the_mode_of_a_new_one(tmp_path, umask):
    """The replacement is a new file (a rename), so an older file's mode does not carry over, e.g. a 0600 file
    written before atomic_path honoured the umask."""
    path = tmp_path / "f.bin"
    path.write_bytes(b"old")
    path.chmod(0o600)
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"new")
    assert path.read_bytes() == b"new" and mode(path) == MODES[umask]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "f.npz"
    path.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(path) as tmp:
            assert tmp.parent == tmp_path and tmp.name.startswith(".f.npz.") and tmp.suffix == ".npz"
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.npz"]


def test_two_writers_get_distinct_temporaries(tmp_path):
    with atomic_path(tmp_path / "a.txt") as one, atomic_path(tmp_path / "a.txt") as two:
        assert one != two and one.is_file() and two.is_file()
        one.write_text("1")
        two.write_text("2")
    assert (tmp_path / "a.txt").read_text() == "1"       # the last to finish (the outer one) wins
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_every_writer_of_the_package_gives_the_mode_open_gives(tmp_path, umask):
    """The writers that go through atomic_path (tests/test_layout.py: no other module renames a temporary file):
    labels.npz, labels.json, the checkpoint, the viewer HTML, the C++ header (the index and the flow records:
    below; the exported model: the last test)."""
    from occflownet.contract.cpp_header import write_header
    from occflownet.labels.config import LabelConfig
    from occflownet.labels.npz import write_labels_npz
    from occflownet.labels.pipeline import _check_settings
    from occflownet.model import create_model, get_preset
    from occflownet.model.checkpoint import save_checkpoint
    from occflownet.viewer import ViewGrid, write_viewer

    grid = np.full((200, 200, 16), 17, np.uint8)
    written = [
        write_labels_npz(tmp_path / "gts" / "labels.npz", grid, grid, grid) or tmp_path / "gts" / "labels.npz",
        (_check_settings(tmp_path / "gts2", LabelConfig(), overwrite=False), tmp_path / "gts2" / "labels.json")[1],
        save_checkpoint(tmp_path / "run" / "last.pt", create_model(get_preset("tiny"), seed=0), get_preset("tiny")),
        write_viewer(tmp_path / "view.html", [ViewGrid("labels", grid)]),
        write_header(tmp_path / "contract.hpp"),
    ]
    assert {p.name: mode(p) for p in written} == {p.name: MODES[umask] for p in written}


def run_cli(args: list[str], mask: int) -> None:
    """``python -m occflownet ARGS`` as a user's shell with umask ``mask`` runs it."""
    run = subprocess.run([sys.executable, "-m", "occflownet", *args], umask=mask, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr


@pytest.mark.parametrize("mask", [0o022, 0o077], ids=["umask022", "umask077"])
def test_a_synthetic_world_and_its_index_have_the_mode_open_gives(tmp_path, mask):
    """``synth`` (images, tables, labels.npz) and ``prepare`` (index.npz/json, flow records, class counts): every
    file the two commands write."""
    root = tmp_path / "world"
    run_cli(["synth", "--out", str(root), "--scenes", "1", "--frames", "2", "--seed", "3", "--width", "160",
             "--height", "90", "--margin", "60", "--no-progress"], mask)
    run_cli(["prepare", "--dataroot", str(root), "--quiet"], mask)
    files = sorted(p for p in root.rglob("*") if p.is_file())
    names = {p.name for p in files}
    assert {"labels.npz", "index.npz", "index.json", "flow.npz", "sample.json"} <= names, names
    assert not [p.name for p in files if p.name.startswith(".")]          # no temporary left behind
    assert {str(p.relative_to(root)): oct(mode(p)) for p in files} == \
        {str(p.relative_to(root)): oct(MODES[mask]) for p in files}


def test_an_exported_model_is_0644_under_umask_022(tmp_path):
    """``occflownet export`` run as a user would, under the common umask 022 (one export: ~45 s on 2 cores; under
    077 the mode, 0600, is what mkstemp gave before whatever the umask, so that case would show nothing new)."""
    mask = 0o022
    out = tmp_path / "models" / "model.onnx"
    run_cli(["export", "--preset", "tiny", "--random-init", "--out", str(out)], mask)
    assert mode(out) == MODES[mask]
    assert sorted(p.name for p in out.parent.iterdir()) == ["model.onnx"]
