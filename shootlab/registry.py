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
``shootlab.records``   ``recipe(**options) -> (table, columns, description)``: an example record
                       for ``shootlab simulate NAME`` (:mod:`shootlab.cli`, ``_simulate``)
``shootlab.commands``  ``add_command(subcommands)``: adds the sub-command ``NAME`` to the
                       ``shootlab`` parser (its ``func`` default runs it), e.g. ``shootlab demo``
``shootlab.problems``  a factory of a study problem: a BVP family that the study commands sweep
=====================  ==========================================================================

The engine itself names no application package: what is installed is what is found.  Nothing is
imported until an entry is loaded, and the lists are read once per process.
"""
from __future__ import annotations

import functools
from importlib.metadata import EntryPoint, entry_points

__all__ = ["GROUPS", "entries", "names", "find", "load"]

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
