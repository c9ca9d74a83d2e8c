import subprocess
import sys

from occflownet.cli import VERBS, build_parser


def test_all_design_verbs_exist():
    assert set(VERBS) == {"synth", "labels", "prepare", "train", "eval", "export", "predict", "serve", "quickstart",
                          "view", "recipes"}


def test_recipes_lists_every_recipe_with_its_figure(capsys):
    from occflownet.cli import main
    from occflownet.train.recipes import RECIPES

    assert main(["recipes", "--names"]) == 0
    assert capsys.readouterr().out.split() == list(RECIPES)
    assert main(["recipes"]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][1:]
    assert len(table) == len(RECIPES) and "**recommended** (default)" in table[0]
    for line, r in zip(table, RECIPES.values()):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert r.name in cells[0] and cells[1] == r.supervises and cells[4] == r.source
        assert (cells[2] == "not measured") == (r.step_seconds is None)


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


def test_the_command_line_starts_without_the_serve_extra():
    """A training install (no pydantic-settings): every verb parses; `serve` says which extra it needs."""
    code = ("import sys; sys.modules['pydantic_settings'] = None; from occflownet.cli import build_parser, main; "
            "p = build_parser(); p.parse_args(['train', '--dataroot', 'd', '--out', 'o']); "
            "sub = next(a for a in p._actions if a.dest == 'verb').choices['serve']; print(sub.format_help()); "
            "sys.exit(main(['serve']))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 2 and "needs the serve extra" in res.stderr, res.stderr
    assert "needs the serve extra" in res.stdout
