"""The options of `synth`, `prepare`, `labels`, `eval`, `export` and `view` are the fields of their configuration
dataclasses (``occflownet/options.py``): every field is an option whose default is the field's, shown in ``--help``;
no options give the dataclass's defaults; the verb's other options (paths, ``--quiet``) restate no default; a value
below a field's minimum or outside its choices is refused, on the command line with a one-line message naming the
option and in Python by the dataclass itself."""
from __future__ import annotations

import dataclasses

import pytest

from occflownet.cli import build_parser, main
from occflownet.data.prepare import PrepareConfig
from occflownet.eval.evaluate import EvalConfig
from occflownet.export.config import ExportConfig
from occflownet.labels import LabelConfig, LabelRun
from occflownet.options import config_kwargs
from occflownet.synth.generate import SynthConfig
from occflownet.synth.layout import WorldConfig
from occflownet.viewer import ViewConfig

# verb: (the arguments it requires, its configuration dataclasses)
VERBS = {
    "synth": (["--out", "w"], (SynthConfig, WorldConfig)),
    "prepare": (["--dataroot", "w"], (PrepareConfig,)),
    "labels": (["--dataroot", "w"], (LabelRun, LabelConfig)),
    "eval": (["--model", "m.onnx", "--dataroot", "w"], (EvalConfig,)),
    "export": (["--checkpoint", "c.pt", "--out", "m.onnx"], (ExportConfig,)),
    "view": (["g.npy", "--out", "v.html"], (ViewConfig,)),
}
NOT_OPTIONS = {"raster_res", "ego_box", "grid"}      # fields no command line sets (WorldConfig, LabelConfig)
# the verb-only options that hold a default: the model source's seed, shared with `predict` (commands/model_source.py)
RESTATED = {("export", "seed")}


def _parser(verb: str):
    return next(a for a in build_parser()._actions if a.dest == "verb").choices[verb]


def _option_fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.name not in NOT_OPTIONS]


def _shown(value) -> str:
    """A default as ``--help`` shows it."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, tuple):
        return " ".join(map(str, value))
    return repr(value) if isinstance(value, str) else str(value)


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_every_option_is_a_field_with_its_default(verb):
    required, classes = VERBS[verb]
    parser = _parser(verb)
    actions = {a.dest: a for a in parser._actions}
    fields = {f.name: f for cls in classes for f in _option_fields(cls)}
    for name, f in fields.items():
        action = actions[name]                                    # every field is an option ...
        assert action.default == f.default, (verb, name)         # ... with the field's default, shown in --help
        if f.default is not None:
            assert f"(default: {_shown(f.default)})" in action.help, (verb, name, action.help)
    for dest, action in actions.items():                          # the verb's own options restate no default
        if dest not in fields and dest != "help" and (verb, dest) not in RESTATED:
            assert action.default in (None, False, []), (verb, dest, action.default)
    args = parser.parse_args(required)                            # no options: the dataclasses' defaults
    for cls in classes:
        assert cls(**config_kwargs(args, cls, skip=NOT_OPTIONS)) == cls(), (verb, cls.__name__)


def _bad_values():
    """(verb, class, field, the value refused, the command-line words that give it)."""
    for verb, (_, classes) in sorted(VERBS.items()):
        for cls in classes:
            for f in _option_fields(cls):
                minimum, choices = f.metadata.get("minimum"), f.metadata.get("choices")
                if minimum is not None:
                    kind = type(f.default[0] if isinstance(f.default, tuple) else f.default or minimum)
                    bad = kind(minimum - 1)
                    value = (bad,) * len(f.default) if isinstance(f.default, tuple) else bad
                    yield pytest.param(verb, cls, f.name, value, [str(bad)] * len(f.default)
                                       if isinstance(f.default, tuple) else [str(bad)], id=f"{verb}-{f.name}-min")
                if choices is not None:
                    yield pytest.param(verb, cls, f.name, "bogus", ["bogus"], id=f"{verb}-{f.name}-choice")


@pytest.mark.parametrize("verb, cls, name, value, words", list(_bad_values()))
def test_a_bad_value_is_refused_naming_the_option(verb, cls, name, value, words, capsys):
    flag = next(a for a in _parser(verb)._actions if a.dest == name).option_strings[0]
    with pytest.raises(SystemExit) as refused:
        main([verb, *VERBS[verb][0], flag, *words])
    assert refused.value.code == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert message.startswith(f"occflownet {verb}: error: argument {flag}: "), message
    assert ("must be at least" if value != "bogus" else "invalid choice") in message
    with pytest.raises(ValueError, match=f"^{name} must be"):   # the same check for Python callers
        cls(**{name: value})


def test_every_verb_with_a_minimum_or_choices_is_covered():
    covered = {p.values[0] for p in _bad_values()}
    assert covered == {"synth", "prepare", "labels", "eval", "export"}      # view's options are paths and a title
