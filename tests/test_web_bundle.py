"""The viewer's committed script is what scripts/build-web builds from today's web/ (npm ci from the lock file, then
esbuild), byte for byte: the bundle is a build output, and a change to web/ without a rebuild, or a hand edit of the
bundle, fails here. Needs node and npm (and the npm registry for `npm ci`); skipped with the reason where either is
missing."""
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("npm") is None or shutil.which("node") is None, reason="node and npm not installed")
def test_the_committed_bundle_is_what_the_build_writes():
    done = subprocess.run(["bash", str(REPO / "scripts" / "build-web"), "--check"], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "is what web/ builds" in done.stdout


def test_the_bundle_is_marked_generated():
    attributes = (REPO / ".gitattributes").read_text()
    assert "occflownet/viewer/assets/occflownet-web.js linguist-generated=true" in attributes
