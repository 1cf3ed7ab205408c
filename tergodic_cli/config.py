"""Stage configs as JSON: one dataclass per stage, saved as ``config.json`` beside its artefact.

:class:`Config` gives a dataclass ``to_dict`` (tuples as lists, nested dataclasses as dicts) and
``from_dict`` (the reverse, with unknown keys and wrong types refused in one line); nested
dataclasses need not derive from it. :func:`write_config` / :func:`read_config` put such dicts
into a file under a ``kind`` that names the verb able to repeat it.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path

from tergodic_cli.errors import TergodicError, require

CONFIG_FILE = "config.json"
#: The layout version :func:`write_config` writes and :func:`read_config` reads.
CONFIG_VERSION = 1


def to_dict(config) -> dict:
    """A config dataclass as JSON-ready values (:meth:`Config.to_dict`; any dataclass).

    Parameters
    ----------
    config : dataclass instance
        Or, in the recursion, any of its values.

    Returns
    -------
    dict
        Field name -> JSON-ready value (tuples as lists, numpy values as Python ones).
    """
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return {f.name: to_dict(getattr(config, f.name)) for f in dataclasses.fields(config)}
    if isinstance(config, (tuple, list)):
        return [to_dict(v) for v in config]
    return config.tolist() if hasattr(config, "tolist") else config  # numpy arrays and scalars


_FIX = "use a config.json written by tergodic, or correct it"


def from_dict(cls, d: dict, what: str | None = None):
    """The config :func:`to_dict` wrote, as ``cls`` (:meth:`Config.from_dict`; any dataclass).

    Parameters
    ----------
    cls : dataclass type
    d : dict
        Field name -> value; missing keys keep their defaults.
    what : str, optional
        How the config is named in an error (default: the class name).

    Returns
    -------
    object
        An instance of ``cls``; an unknown key or a value of the wrong type raises
        :class:`~tergodic_cli.errors.TergodicError` naming it.
    """
    where = what or cls.__name__
    require(isinstance(d, dict), f"{where} is not a JSON object", _FIX)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(d) - names)
    if unknown:
        raise TergodicError(f"{where} has an unknown key '{unknown[0]}'", _FIX)
    return cls(**{k: _coerce(hints[k], v, f"{where}.{k}") for k, v in d.items()})


def _coerce(hint, value, where: str):
    """``value`` as the type ``hint`` says: None where optional, tuples, nested dataclasses, numbers."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        if len(options) > 1:
            return value  # a free union: the stage's validation checks it
        hint = options[0]
        args = typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return from_dict(hint, value, where)
    origin = typing.get_origin(hint)
    if origin is tuple:
        require(isinstance(value, (list, tuple)), f"{where} is not a list", _FIX)
        kinds = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        require(not kinds or len(kinds) == len(value), f"{where} needs {len(kinds)} values, got {len(value)}", _FIX)
        return tuple(_coerce(k, v, f"{where}[{i}]") for i, (k, v) in enumerate(zip(kinds or [typing.Any] * len(value), value)))
    if hint is float:
        require(isinstance(value, (int, float)) and not isinstance(value, bool), f"{where} is not a number", _FIX)
        return float(value)
    if hint in (int, bool, str):
        require(isinstance(value, hint) and (hint is bool or not isinstance(value, bool)),
                f"{where} is not {'an' if hint is int else 'a'} {hint.__name__}", _FIX)
    return value


@dataclasses.dataclass(frozen=True)
class Option:
    """How a verb offers a config field on its command line: the field's ``metadata["option"]``
    (:func:`option`). The verbs build their options from these (``commands/_options.py``), so a
    field's type, default, help and unit are declared once, here, beside the field.

    Attributes
    ----------
    flag : str
        The option, e.g. ``"--agent-radius"``, or ``"--dry-run/--no-dry-run"`` (a switch with its
        negation); the verb's parameter is named after it (``agent_radius``).
    help : str
        What it sets, without its unit and default (those are appended).
    unit : str, optional
        The value's unit ("m", "N", "m/s"), appended to the help.
    group : str, optional
        The runs it applies to ("robot", "pybullet", "franka", "closed loop"), shown first as "[group]".
    default : str, optional
        The "[default: ...]" text where the field's default does not say it (a None that means
        something, e.g. "20% of --force").
    type : type, optional
        The value's type on the command line where it is not the field's (e.g. ``str`` for a pose
        typed as "x,y,z"); ``parse`` turns it into the field's value.
    parse : callable, optional
        text -> the field's value; with ``sets``, a tuple of the values of those fields.
    sets : tuple of str, optional
        The fields the option sets, where it sets more than its own (e.g. ``--workspace``: the box's
        two corners).
    short : str, optional
        A one-letter alias ("-o").
    metavar : str, optional
        How the value is shown in the help.
    """

    flag: str
    help: str
    unit: str | None = None
    group: str | None = None
    default: str | None = None
    type: typing.Any = None
    parse: typing.Callable | None = None
    sets: tuple[str, ...] | None = None
    short: str | None = None
    metavar: str | None = None

    @property
    def name(self) -> str:
        """The verb's parameter name (``--agent-radius`` -> ``agent_radius``)."""
        return self.flag.split("/")[0].lstrip("-").replace("-", "_")

    def help_text(self, shown_default=None) -> str:
        """The help line: "[group] help, unit [default: ...].".

        Parameters
        ----------
        shown_default : str, optional
            The default to show when :attr:`default` is None and the command line does not show it itself.

        Returns
        -------
        str
        """
        text = (f"[{self.group}] " if self.group else "") + self.help.rstrip(".")
        if self.unit:
            text += f", {self.unit}"
        default = self.default if self.default is not None else shown_default
        return text + (f" [default: {default}]" if default is not None else "") + "."


def option(flag: str, help: str, **kw) -> dict:
    """A field's metadata that offers it as a verb option: ``field(default=..., metadata=option(...))``.

    Parameters
    ----------
    flag, help : str
        See :class:`Option`.
    **kw
        The other :class:`Option` attributes.

    Returns
    -------
    dict
        ``{"option": Option(...)}``.
    """
    return {"option": Option(flag, help, **kw)}


def options_of(cls) -> list[tuple[str, Option]]:
    """The (field name, :class:`Option`) pairs of a config dataclass, in field order.

    Parameters
    ----------
    cls : dataclass type

    Returns
    -------
    list of (str, Option)
    """
    return [(f.name, f.metadata["option"]) for f in dataclasses.fields(cls) if "option" in f.metadata]


def parse_floats(text: str | None, n: int | None, option: str, example: str) -> tuple[float, ...] | None:
    """Parse ``"a,b,c"`` into ``n`` floats (any count when ``n`` is None: the stage checks it), None into None,
    or raise a one-line error naming ``option``.

    Parameters
    ----------
    text : str or None
    n : int or None
        How many numbers it must hold.
    option, example : str
        The option's name and an example value, for the error.

    Returns
    -------
    tuple of float, or None
    """
    if text is None:
        return None
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        count = f"{n} " if n is not None else ""
        raise TergodicError(f"{option} '{text}' is not {count}comma-separated numbers", f"e.g. {option} {example}") from None
    if n is not None and len(values) != n:
        raise TergodicError(f"{option} needs {n} numbers, got {len(values)}", f"e.g. {option} {example}")
    return values


class Config:
    """Mixin for config dataclasses: ``to_dict`` / ``from_dict`` round-trip through JSON."""

    to_dict = to_dict
    from_dict = classmethod(from_dict)


def override(saved, now, given, renamed: dict | None = None):
    """``saved`` with the fields of the options ``given`` on the command line taken from ``now``.

    Parameters
    ----------
    saved, now : dataclass
        The loaded config and the one the command line built (same class).
    given : set of str
        The verb's option names given on the command line.
    renamed : dict, optional
        Option name -> the fields it sets, where they differ from its name.

    Returns
    -------
    dataclass
        A copy of ``saved``.
    """
    fields = {f for opt in given for f in (renamed or {}).get(opt, (opt,)) if hasattr(now, f)}
    return dataclasses.replace(saved, **{f: getattr(now, f) for f in fields})


def write_config(path: str | Path, kind: str, **sections) -> None:
    """Write a loadable ``config.json`` atomically.

    Parameters
    ----------
    path : str or Path
        The file to write.
    kind : str
        What the config repeats (``"tergodic.capture_config"``, ...), checked on load.
    **sections
        Named parts: :class:`Config` instances or JSON-ready values.
    """
    from tergodic_cli.atomic import write_json

    sections = {k: to_dict(v) for k, v in sections.items()}
    write_json(Path(path), {"kind": kind, "version": CONFIG_VERSION, **sections})


def read_config(path: str | Path, kind: str, fix: str, sections: tuple[str, ...] | None = None) -> dict:
    """Read a ``config.json`` that :func:`write_config` wrote with ``kind``.

    Parameters
    ----------
    path : str or Path
        The file given to ``--config``.
    kind : str
        The kind it must have.
    fix : str
        What to do instead, for the one-line error.
    sections : tuple of str, optional
        The top-level keys the kind has besides ``kind`` and ``version``; another one is refused.

    Returns
    -------
    dict
        The file's sections (still plain dicts; each stage's ``from_dict`` checks its own).
    """
    path = Path(path)
    require(path.is_file(), f"--config {path} does not exist", fix)
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TergodicError(f"--config {path} is not readable JSON ({type(exc).__name__})", fix) from None
    require(isinstance(d, dict) and d.get("kind") == kind, f"--config {path} is not a {kind.split('.')[-1].replace('_', ' ')}",
            fix)
    version = d.get("version", CONFIG_VERSION)  # hand-written ones may leave it out
    require(version == CONFIG_VERSION and not isinstance(version, bool), f"--config {path} has version {version!r}; this tergodic reads version {CONFIG_VERSION}",
            "write it again with this tergodic (or use the tergodic that wrote it)")
    if sections is not None:
        unknown = sorted(set(d) - {"kind", "version", *sections})
        if unknown:
            raise TergodicError(f"--config {path} has an unknown key '{unknown[0]}'", f"it takes {', '.join(sections)}; {fix}")
    return d
