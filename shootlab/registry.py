"""Plugins by entry point: the models, candidate libraries, example records, commands and study
problems that installed packages declare in their ``pyproject.toml``.

    [project.entry-points."shootlab.models"]
    drive = "mypackage.drive:model"

=====================  ==========================================================================
group                  an entry ``name = "module:object"`` names
=====================  ==========================================================================
``shootlab.models``    an :class:`~shootlab.estimation.IdentificationModel` or a factory of one
                       (``shootlab estimate --model NAME``; :func:`shootlab.estimation.lookup.resolve_model`)
``shootlab.libraries`` the candidate effects of the model ``NAME``: a function of the model
                       returning a :class:`~shootlab.diagnosis.Library` (``shootlab diagnose``)
``shootlab.records``   a :class:`Record`: an example record for ``shootlab simulate NAME``, its
                       recipe and the options it declares (``shootlab simulate NAME --help``)
``shootlab.commands``  ``add_command(subcommands)``: adds the sub-command ``NAME`` to the
                       ``shootlab`` parser (its ``func`` default runs it), e.g. ``shootlab demo``
``shootlab.problems``  a factory of a study problem: a BVP family that the study commands sweep
=====================  ==========================================================================

The engine itself names no application package: what is installed is what is found.  Nothing is
imported until an entry is loaded, and the lists are read once per process.
"""
from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Callable, Sequence

__all__ = ["GROUPS", "entries", "names", "find", "load", "Option", "Record"]

#: kind -> (entry-point group, noun used in messages)
GROUPS = {
    "models": ("shootlab.models", "model"),
    "libraries": ("shootlab.libraries", "library"),
    "records": ("shootlab.records", "record"),
    "commands": ("shootlab.commands", "command"),
    "problems": ("shootlab.problems", "problem"),
}


def _group(kind: str) -> tuple[str, str]:
    try:
        return GROUPS[kind]
    except KeyError:
        raise ValueError(f"unknown kind of plugin {kind!r}: one of {', '.join(GROUPS)}") from None


@functools.cache
def entries(kind: str) -> dict[str, EntryPoint]:
    """The installed entry points of a kind, name -> entry point, sorted by name (the first one
    found wins for a name declared twice)."""
    group, _ = _group(kind)
    out: dict[str, EntryPoint] = {}
    for ep in sorted(entry_points(group=group), key=lambda ep: ep.name):
        out.setdefault(ep.name, ep)
    return out


def names(kind: str) -> list[str]:
    """The installed names of a kind (``names("models")`` -> ``['msd', 'flexible', ...]``)."""
    return list(entries(kind))


def find(kind: str, name: str) -> EntryPoint | None:
    """The entry point ``name`` of a kind, or None."""
    return entries(kind).get(name)


def load(kind: str, name: str):
    """The object the entry ``name`` of a kind points to.  ValueError with the installed names if
    there is none (``unknown model 'x': installed models are msd, flexible, ...``) or with the
    cause if its module does not import."""
    _, noun = _group(kind)
    ep = find(kind, name)
    if ep is None:
        have = names(kind)
        listed = ", ".join(have) if have else "none (is the package installed, e.g. pip install -e .?)"
        raise ValueError(f"unknown {noun} {name!r}: installed {_plural(noun)} are {listed}")
    try:
        return ep.load()
    except Exception as exc:
        raise ValueError(f"{noun} {name!r} ({ep.value}) does not load: {type(exc).__name__}: {exc}") from None


def _plural(noun: str) -> str:
    return noun[:-1] + "ies" if noun.endswith("y") else noun + "s"


# ----------------------------------------------------------------------------- example records
@dataclass(frozen=True)
class Option:
    """A keyword option of an example record, as ``shootlab simulate NAME --NAME VALUE`` offers it.

    name     a keyword argument of the record's recipe (the flag is ``--name``, ``_`` as ``-``)
    kind     ``int``, ``float``, ``str`` or ``bool`` (a bool is ``--name`` / ``--no-name``)
    default  the value when the option is not given (None: the recipe's own choice, said in ``help``)
    help     one line: what it sets, in which unit
    choices  the allowed values, if they are few
    low      for a number: the least value (exclusive where ``strict``); values must be finite
    """

    name: str
    kind: type = float
    default: Any = None
    help: str = ""
    choices: Sequence | None = None
    low: float | None = None
    strict: bool = False

    def __post_init__(self):
        if not self.name.isidentifier():
            raise ValueError(f"option {self.name!r}: the name must be a Python identifier")
        if self.kind not in (int, float, str, bool):
            raise ValueError(f"option {self.name!r}: kind must be int, float, str or bool, got {self.kind!r}")


@dataclass(frozen=True)
class Record:
    """An example record (entry points ``shootlab.records``): ``recipe(seed=..., **options)`` returns
    ``(table, columns, description)`` — the columns by name (``t`` first), their order, and a
    one-line description of what was simulated; ``options`` declares its keyword arguments besides
    ``seed`` (each one of them, with its default: the recipe takes them all).  Calling the record
    calls its recipe with the declared defaults for the options not given."""

    recipe: Callable[..., tuple[dict, list[str], str]]
    description: str
    options: tuple[Option, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "options", tuple(self.options))
        names = [o.name for o in self.options]
        if len(set(names)) < len(names) or {"seed", "out"} & set(names):
            raise ValueError(f"record options {names}: each name once, and not seed or out (simulate's own)")
        try:
            takes = inspect.signature(self.recipe).parameters
        except (TypeError, ValueError):
            return
        missing = [n for n in ["seed", *names] if n not in takes]
        if missing and not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in takes.values()):
            raise ValueError(f"record options {missing} are not keyword arguments of its recipe "
                             f"{getattr(self.recipe, '__qualname__', self.recipe)!r}")

    def __call__(self, seed: int = 0, **options) -> tuple[dict, list[str], str]:
        unknown = sorted(set(options) - {o.name for o in self.options})
        if unknown:
            raise ValueError(f"{', '.join(unknown)}: not an option of this record; its options are "
                             f"{', '.join(o.name for o in self.options) or '(none)'}")
        values = {o.name: options.get(o.name, o.default) for o in self.options}
        return self.recipe(seed=seed, **values)
