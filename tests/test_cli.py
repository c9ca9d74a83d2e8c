import subprocess
import sys

from occflownet.cli import VERBS, build_parser


def test_all_design_verbs_exist():
    assert set(VERBS) == {"synth", "labels", "prepare", "train", "eval", "export", "predict", "serve", "quickstart",
                          "view"}


def test_help_runs_without_torch():
    code = ("import sys; from occflownet.cli import build_parser; build_parser().format_help(); "
            "assert 'torch' not in sys.modules, 'CLI start-up imported torch'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_parser_builds():
    assert "synth" in build_parser().format_help()


def test_help_runs_without_the_training_extras():
    """A serving install (no torch, scipy or numba) still starts the command line."""
    code = ("import sys; from occflownet.cli import build_parser; build_parser().format_help(); "
            "bad = [m for m in ('torch', 'scipy', 'numba') if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)
