"""Command-line options derived from a configuration dataclass: one field, one option, one default, one help text.

A field declared with :func:`option` carries its help text and choices (and, where the option's name is not the
field's, that name) in its ``dataclasses`` metadata; :func:`add_options` turns the fields into ``argparse``
options (``int``/``float``/``str`` with the annotation's type, ``bool`` as ``--x/--no-x``, the field's default),
:func:`config_kwargs` reads them back, and :func:`config_argv` writes the options that give a configuration again
(the quickstart prints the ``occflownet train`` command of the run it starts). Nothing here knows a particular
configuration; ``commands/train.py`` and ``commands/quickstart.py`` call these with ``TrainConfig`` and
``QuickstartConfig``.

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


def option(default, help: str, *, choices: Sequence | None = None, flag: str | None = None):
    """A dataclass field with its command-line description: ``help`` (the field's documentation), ``choices``
    (the allowed values, checked by argparse), ``flag`` (the option's name without dashes; default: the field's
    name with ``-`` for ``_``)."""
    return dataclasses.field(default=default, metadata={"help": help, "choices": choices, "flag": flag})


def _flag(f: dataclasses.Field) -> str:
    return "--" + (f.metadata.get("flag") or f.name.replace("_", "-"))


def _value_type(cls, f: dataclasses.Field) -> type:
    """The annotation's type with ``None`` left out: ``int | None`` → int."""
    return _plain_type(typing.get_type_hints(cls)[f.name], f"{cls.__name__}.{f.name}")


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


def add_options(parser: argparse.ArgumentParser, cls, *, skip: Sequence[str] = (), required: Sequence[str] = (),
                defaults: dict | None = None) -> None:
    """One option per field of dataclass ``cls`` (but those in ``skip``): ``required`` ones must be given;
    ``defaults`` replaces a field's default on the command line (the help says what ``None`` means)."""
    defaults = defaults or {}
    for f in _fields(cls, skip):
        kind = _value_type(cls, f)
        default = defaults.get(f.name, f.default)
        kw = dict(dest=f.name, help=f.metadata.get("help", ""), default=None if f.name in required else default)
        if kind is bool:
            kw.update(action=argparse.BooleanOptionalAction, help=kw["help"] + f" (default: {_on_off(default)})")
        else:
            kw.update(type=kind, choices=f.metadata.get("choices"), required=f.name in required,
                      metavar=None if f.metadata.get("choices") else _flag(f)[2:].upper().replace("-", "_"))
            if default is not None and f.name not in required:
                kw["help"] += f" (default: {default!r})" if kind is str else f" (default: {default})"
        parser.add_argument(_flag(f), **kw)


def _on_off(value: bool) -> str:
    return "on" if value else "off"


def config_kwargs(args: argparse.Namespace, cls, *, skip: Sequence[str] = ()) -> dict:
    """The parsed options of :func:`add_options` as keyword arguments of ``cls``."""
    return {f.name: getattr(args, f.name) for f in _fields(cls, skip)}


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
