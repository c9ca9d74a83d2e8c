"""The README and docs/ describe today's tools: every `occflownet ...` command line of a code block parses with
today's command line, every `occflownet VERB --option` named in the prose is an option of that verb, every
benchmark they run (`python -m benchmarks.perf.NAME`, `python -m benchmarks.studies.NAME`, `python benchmarks/X.py`)
exists and has the options they give it (in its own file or a benchmarks module it imports), every relative link
(and its #anchor) resolves, and every recipe's docs page exists. Commands with placeholders in brackets (`[--seed S]`),
alternatives (`a|b`), ellipses or a placeholder verb (`occflownet VERB --help`) are usage summaries, not command
lines, and are skipped; one- or two-letter capitals (`--seed S`) are placeholders; a span like
`occflownet serve: ...` is a message the tools print."""
import re
import shlex
from pathlib import Path

import pytest

from occflownet.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), *sorted(REPO.glob("*/README.md"))]
USAGE = re.compile(r"[\[\]|<>…]|\.\.\.")
BENCHMARK = ("python benchmarks/", "python -m benchmarks.")


def _commands(text: str) -> list[tuple[str, bool]]:
    """(command, whole) of a page: the lines of code blocks (fenced or indented; a trailing backslash continues the
    line), whole command lines, and the inline code spans that start with a command, which may name a verb and
    some of its options only."""
    found, block, pending = [], False, ""
    for line in text.splitlines():
        if line.strip().startswith("```"):
            block = not block
            continue
        if not (block or line.startswith("    ")):
            pending = ""
            continue
        pending += line.strip().rstrip("\\").strip() + " "
        if line.rstrip().endswith("\\"):
            continue
        command = pending.strip().lstrip("$ ").split(" # ")[0].split("  #")[0].strip()
        found += [(part.strip(), True) for part in re.split(r"&&|;", command)]
        pending = ""
    spans = re.findall(r"`((?:occflownet|python benchmarks/|python -m benchmarks\.)[^`]*)`", text)
    found += [(" ".join(span.split()), False) for span in spans]
    return [(c, whole) for c, whole in found if c.startswith(("occflownet ", *BENCHMARK))]


def _cases():
    for page in PAGES:
        for command, whole in _commands(page.read_text()):
            if not USAGE.search(command) and not re.match(r"occflownet [a-z]+:", command):
                yield pytest.param(page.relative_to(REPO), command, whole,
                                   id=f"{page.name}:{command[:60]}{'' if whole else ' (prose)'}")


def _verb_options(verb: str) -> set[str] | None:
    sub = next(a for a in build_parser()._actions if a.dest == "verb").choices.get(verb)
    return None if sub is None else {o for a in sub._actions for o in a.option_strings}


@pytest.mark.parametrize("page,command,whole", list(_cases()))
def test_every_command_line_in_the_docs_parses(page, command, whole):
    words = shlex.split(command)
    if words[0] == "occflownet" and words[1].isupper():
        pytest.skip("a verb placeholder")
    if words[1] == "-m" and words[2].rsplit(".", 1)[-1].isupper():
        pytest.skip("a benchmark placeholder (benchmarks.perf.NAME)")
    if words[0] == "occflownet":
        options = _verb_options(words[1])
        assert options is not None, f"{page}: `{command}`: occflownet has no verb {words[1]!r}"
        if whole:               # placeholders of a number (S, N, K) read as 1
            try:
                build_parser().parse_args([re.sub(r"^[A-Z]{1,2}$", "1", w) for w in words[1:]])
            except SystemExit as exc:
                assert exc.code == 0, f"{page}: `{command}` does not parse with today's CLI"
        unknown = [w for w in words[2:] if w.startswith("--") and w.split("=")[0] not in options]
        assert not unknown, f"{page}: `{command}`: occflownet {words[1]} has no option {unknown}"
        return
    script = words[2] if words[1] == "-m" else words[1]
    source = REPO / (script.replace(".", "/") + ".py" if words[1] == "-m" else script)
    assert source.is_file(), f"{page}: `{command}` names {script}, which does not exist"
    text = _benchmark_text(source)
    for option in (w.split("=")[0] for w in words if w.startswith("--")):
        assert f'"{option}"' in text, f"{page}: {script} has no option {option}"


def _benchmark_text(source: Path) -> str:
    """A benchmark's source and that of the benchmarks modules it imports (where shared options are defined)."""
    text = source.read_text()
    for module in re.findall(r"^from (benchmarks\.[\w.]+) import", text, flags=re.M):
        text += (REPO / (module.replace(".", "/") + ".py")).read_text()
    return text


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but - and _ dropped, spaces to -."""
    heading = re.sub(r"[`*]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", heading).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    return {_slug(m) for m in re.findall(r"^#+ (.+)$", page.read_text(), flags=re.M)}


def _check_target(page: Path, target: str) -> str | None:
    """None if ``target`` (a relative link of ``page``) resolves, else why not."""
    path, _, anchor = target.partition("#")
    file = (page.parent / path).resolve() if path else page
    if not file.exists():
        return f"{page.relative_to(REPO)}: link {target} names a missing file"
    if anchor and file.suffix == ".md" and anchor not in _anchors(file):
        return f"{page.relative_to(REPO)}: link {target} names a missing heading"
    return None


def test_every_relative_link_resolves():
    problems = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if not re.match(r"[a-z]+:", target):
                problems.append(_check_target(page, target))
    assert not [p for p in problems if p], [p for p in problems if p]


def test_every_recipe_names_a_page_that_exists():
    from occflownet.train.recipes import RECIPES

    problems = [_check_target(REPO / "README.md", r.source) for r in RECIPES.values()]
    assert not [p for p in problems if p]
