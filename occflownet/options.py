"""Command-line options derived from a configuration dataclass: one field, one option, one default, one help text.

A field declared with :func:`option` carries in its ``dataclasses`` metadata its help text, its choices, its
smallest allowed value, the ``--help`` group it is listed in, and (where the option's name is not the field's) that
name; :func:`add_options` turns the fields into ``argparse`` options (``int``/``float``/``str`` with the
annotation's type, ``tuple[int, int]`` as two values, ``bool`` as ``--x/--no-x``, the field's default),
:func:`config_kwargs` reads them back, :func:`check_fields` checks a configuration's values against the same
metadata (one loop for every field: configurations call it from ``__post_init__``), and :func:`config_argv` writes
the options that give a configuration again (the quickstart prints the ``occflownet train`` command of the run it
starts). Nothing here knows a particular configuration; the commands call these with their dataclasses.

The same for the fields of a pydantic settings model (``commands/serve.py`` with ``serve.settings.ServeSettings``):
:func:`add_model_options` and :func:`model_kwargs`. Those options default to "not given", so that what the command
line leaves unset comes from where else the model reads (the environment, ``.env``), then its default; the help
shows that default. The model is read through its ``model_fields`` only: pydantic is not imported here.
"""
from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Callable, Sequence


def option(default, help: str, *, choices: Sequence | None = None, flag: str | None = None,
           minimum: float | None = None, group: str | None = None):
    """A dataclass field with its command-line description: ``help`` (the field's documentation), ``choices``
    (the allowed values), ``minimum`` (the smallest allowed value of a number; ``None`` is always allowed),
    ``group`` (the ``--help`` section it is listed in; None: the parser's own list), ``flag`` (the option's name
    without dashes; default: the field's name with ``-`` for ``_``). :func:`check_fields` and argparse check
    ``choices`` and ``minimum``."""
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices, "flag": flag,
                                                        "minimum": minimum, "group": group})


def _flag(f: dataclasses.Field) -> str:
    return "--" + (f.metadata.get("flag") or f.name.replace("_", "-"))


def _value_type(cls, f: dataclasses.Field) -> tuple[type, int | None]:
    """(the annotation's value type with ``None`` left out, the number of values: None for one, n for a
    ``tuple[T, ...]`` of n equal types): ``int | None`` → (int, None), ``tuple[float, float]`` → (float, 2)."""
    hint = typing.get_type_hints(cls)[f.name]
    what = f"{cls.__name__}.{f.name}"
    if typing.get_origin(hint) is tuple:
        args = set(typing.get_args(hint))
        if len(args) != 1:
            raise TypeError(f"{what}: no command-line option for type {hint!r}")
        return _plain_type(args.pop(), what), len(typing.get_args(hint))
    return _plain_type(hint, what), None


def _plain_type(hint, what: str) -> type:
    """``hint`` with ``None`` left out (``int | None`` → int): bool, int, float or str, else a TypeError naming
    ``what``."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    if hint not in (bool, int, float, str):
        raise TypeError(f"{what}: no command-line option for type {hint!r}")
    return hint


def _fields(cls, skip: Sequence[str]) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.name not in skip]


def _checked(kind: type, minimum: float | None, flag: str) -> Callable[[str], object]:
    """argparse ``type`` of a number option with a smallest value: the number, or an error naming the bound."""
    def parse(text: str):
        value = kind(text)
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be at least {minimum:g}, got {text}")
        return value
    parse.__name__ = kind.__name__          # argparse names the type in "invalid int value" messages
    return parse


def add_options(parser: argparse.ArgumentParser, cls, *, skip: Sequence[str] = (), required: Sequence[str] = (),
                defaults: dict | None = None, given_only: bool = False,
                groups: Sequence[tuple[str, str]] = ()) -> None:
    """One option per field of dataclass ``cls`` (but those in ``skip``): ``required`` ones must be given;
    ``defaults`` replaces a field's default in the help (and, unless ``given_only``, on the command line);
    ``given_only``: options left out are absent from the parsed namespace (argparse.SUPPRESS), so that
    :func:`config_kwargs` returns the options given and nothing else. ``groups`` ((name, description) in ``--help``
    order) lists the sections the fields' ``group`` metadata name; a field without a group goes to the parser."""
    defaults = defaults or {}
    sections = {name: parser.add_argument_group(name, description) for name, description in groups}
    for f in _fields(cls, skip):
        (kind, nargs), target = _value_type(cls, f), sections.get(f.metadata.get("group"), parser)
        if f.metadata.get("group") and target is parser:
            raise ValueError(f"{cls.__name__}.{f.name}: group {f.metadata['group']!r} is not among {list(sections)}")
        default = defaults.get(f.name, f.default)
        kw = dict(dest=f.name, help=f.metadata.get("help", ""))
        kw["default"] = argparse.SUPPRESS if given_only else None if f.name in required else default
        if kind is bool:
            kw.update(action=argparse.BooleanOptionalAction, help=kw["help"] + f" (default: {_on_off(default)})")
        else:
            minimum = f.metadata.get("minimum")
            kw.update(type=kind if minimum is None else _checked(kind, minimum, _flag(f)),
                      choices=f.metadata.get("choices"), required=f.name in required,
                      metavar=None if f.metadata.get("choices") else _flag(f)[2:].upper().replace("-", "_"))
            if nargs is not None:
                kw.update(nargs=nargs, metavar=("MIN", "MAX") if nargs == 2 else None)
            if default is not None and f.name not in required:
                shown = " ".join(map(str, default)) if nargs else repr(default) if kind is str else default
                kw["help"] += f" (default: {shown})"
        target.add_argument(_flag(f), **kw)


def _on_off(value: bool) -> str:
    return "on" if value else "off"


def config_kwargs(args: argparse.Namespace, cls, *, skip: Sequence[str] = ()) -> dict:
    """The parsed options of :func:`add_options` as keyword arguments of ``cls`` (with ``given_only``: those
    given); a ``tuple`` field's values as a tuple."""
    kwargs = {f.name: getattr(args, f.name) for f in _fields(cls, skip) if hasattr(args, f.name)}
    return {name: tuple(v) if isinstance(v, list) else v for name, v in kwargs.items()}


def check_fields(obj) -> None:
    """Check every field of dataclass instance ``obj`` against its :func:`option` metadata: a value among
    ``choices``, a number (or each number of a tuple) at least ``minimum``. ValueError naming the field."""
    for f in dataclasses.fields(obj):
        value, allowed, minimum = getattr(obj, f.name), f.metadata.get("choices"), f.metadata.get("minimum")
        if allowed is not None and value not in allowed:
            raise ValueError(f"{f.name} must be one of {tuple(allowed)}, got {value!r}")
        numbers = value if isinstance(value, tuple) else (value,)
        if minimum is not None and any(v is not None and v < minimum for v in numbers):
            raise ValueError(f"{f.name} must be at least {minimum:g}, got {value!r}")


def config_argv(cfg, baseline, *, always: Sequence[str] = ()) -> list[str]:
    """The options that give ``cfg`` when parsed by a parser of :func:`add_options`: the fields named in
    ``always`` and every field whose value differs from ``baseline``'s (the configuration the command line gives
    without options). Floats are written with ``repr``, which reads back to the same number."""
    argv = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.name not in always and value == getattr(baseline, f.name):
            continue
        if isinstance(value, bool):
            argv.append(_flag(f) if value else "--no-" + _flag(f)[2:])
        elif isinstance(value, tuple):
            argv += [_flag(f), *(repr(v) if isinstance(v, float) else str(v) for v in value)]
        elif value is not None:
            argv += [_flag(f), repr(value) if isinstance(value, float) else str(value)]
    return argv


def add_model_options(parser: argparse.ArgumentParser, cls, *, skip: Sequence[str] = (),
                      env: Callable[[str], str] | None = None) -> None:
    """One option per field of the pydantic model ``cls`` (but those in ``skip``), each defaulting to None = not
    given: ``--field-name`` (or ``json_schema_extra={"flag": name}``), the field's description as help with its
    default (and, given ``env``, the variable ``env(field)`` that an unset option falls back to), the annotation's
    type (``X | None`` → X; a ``list`` field takes one string, which the model's validator splits), a ``bool`` as
    ``--x/--no-x``. A default of None or "" is not shown: the description says what it means."""
    for name, info in cls.model_fields.items():
        if name in skip:
            continue
        extra = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
        flag = "--" + (extra.get("flag") or name.replace("_", "-"))
        listed = typing.get_origin(info.annotation) is list
        kind = str if listed else _plain_type(info.annotation, f"{cls.__name__}.{name}")
        notes = []
        if info.default not in (None, ""):
            default = info.default
            shown = _on_off(default) if kind is bool else ",".join(default) if listed else default
            notes.append(f"default: {shown}")
        if env is not None:
            notes.append(f"${env(name)}")
        help = info.description + (f" ({'; '.join(notes)})" if notes else "")
        if kind is bool:
            parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=help)
        else:
            parser.add_argument(flag, dest=name, type=kind, default=None, help=help,
                                metavar=flag[2:].upper().replace("-", "_"))


def model_kwargs(args: argparse.Namespace, cls, *, skip: Sequence[str] = ()) -> dict:
    """The options of :func:`add_model_options` that were given, as keyword arguments of ``cls``."""
    return {name: getattr(args, name) for name in cls.model_fields
            if name not in skip and getattr(args, name) is not None}
