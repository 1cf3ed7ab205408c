"""A verb's options built from the config dataclasses: each field's :class:`~tergodic_cli.config.Option`
(type, default, help, unit) is declared once, beside the field, and becomes a typer option here.

``@with_options(ExploreConfig, ...)`` appends the options of those configs to the verb's own
parameters (its signature is rebuilt with :mod:`inspect`, which typer reads); the verb takes them
as ``**opts`` and turns them back into config fields with :func:`values`.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import types
import typing
from typing import Optional

import typer

from tergodic_cli.config import Option, options_of


def _cli_type(cls, name: str, opt: Option):
    """The option's type on the command line: Option.type, else the field's (Optional when it may be None)."""
    if opt.type is not None:
        return Optional[opt.type]
    hint = typing.get_type_hints(cls)[name]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
        return Optional[inner]
    return hint


def _default(cls, name: str):
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    return f.default if f.default is not dataclasses.MISSING else None


def _text(value) -> str:
    """A default as the command line types it: numbers as %g, tuples comma-separated."""
    if isinstance(value, (tuple, list)):
        return ",".join(_text(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def parameters(cls) -> list[inspect.Parameter]:
    """The typer parameters of a config dataclass' fields that carry an option.

    Parameters
    ----------
    cls : dataclass type

    Returns
    -------
    list of inspect.Parameter
        Keyword-only, named :attr:`Option.name`, with a ``typer.Option`` default.
    """
    out = []
    for name, opt in options_of(cls):
        # typed as text (parsed): not given is None, and the field's default applies (shown as text)
        default = None if opt.parse is not None else _default(cls, name)
        shown = None
        if opt.parse is not None and opt.type is not bool and all(_default(cls, f) is not None for f in opt.sets or (name,)):
            shown = ",".join(_text(_default(cls, f)) for f in opt.sets or (name,))
        flags = [opt.flag] + ([opt.short] if opt.short else [])
        info = typer.Option(default, *flags, help=opt.help_text(shown), metavar=opt.metavar, show_default=opt.default is None)
        out.append(inspect.Parameter(opt.name, inspect.Parameter.KEYWORD_ONLY, default=info,
                                     annotation=_cli_type(cls, name, opt)))
    return out


def with_options(*classes):
    """Decorator: the verb also takes the options of ``classes`` (config dataclasses), as ``**opts``.

    Parameters
    ----------
    *classes : dataclass types
        Their fields with an :class:`~tergodic_cli.config.Option`, in this order, after the verb's own
        parameters.

    Returns
    -------
    callable
        The decorator.
    """
    def wrap(fn):
        sig = inspect.signature(fn)
        own = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
        extra = [p for cls in classes for p in parameters(cls)]
        names = [p.name for p in own + extra]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise TypeError(f"{fn.__name__}: options declared twice: {sorted(dup)}")

        @functools.wraps(fn)
        def verb(*args, **kwargs):
            return fn(*args, **kwargs)

        verb.__signature__ = sig.replace(parameters=own + extra)
        verb.option_classes = classes
        return verb

    return wrap


def values(cls, opts: dict, given: set | None = None) -> dict:
    """The fields of ``cls`` that the options in ``opts`` set, parsed (None values stay None).

    Parameters
    ----------
    cls : dataclass type
    opts : dict
        The verb's parameters (name -> value).
    given : set of str, optional
        Only these parameter names (those given on the command line, :func:`given_options`).

    Returns
    -------
    dict
        Field name -> value; an option with ``sets`` gives each of those fields.
    """
    out = {}
    for name, opt in options_of(cls):
        if opt.name not in opts or (given is not None and opt.name not in given):
            continue
        value = opts[opt.name]
        if opt.parse is not None and value is not None:
            value = opt.parse(value)
        if opt.sets:
            for f, v in zip(opt.sets, value if value is not None else (None,) * len(opt.sets)):
                out[f] = v
        else:
            out[name] = value
    return out


def renamed(cls) -> dict:
    """Option name -> the fields it sets, where they differ from its name (for :func:`~tergodic_cli.config.override`)."""
    return {opt.name: opt.sets or (name,) for name, opt in options_of(cls) if (opt.sets or (name,)) != (opt.name,)}
