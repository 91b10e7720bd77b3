"""The candidate library of a model (docs/design.md §4, step 2): its own (``settings.diagnosis_library``), the mechanical library of a model that declares its mechanics, the installed one for its name (entry points ``shootlab.libraries``, :mod:`shootlab.registry`), or :func:`generic_library` (an offset per measured channel)."""
from __future__ import annotations



from shootlab import registry
from .effects import Effect, Library
from .mechanical import mechanical_library
from shootlab.estimation.model import IdentificationModel


def generic_library(model: IdentificationModel) -> Library:
    """Effects any model has: a constant offset on each measured channel (``offset_<channel>``)."""
    effects = []
    for row, ch in model.channels.items():
        p = f"offset_{ch}"
        if p in model.names or p in model.inputs:
            continue

        def term(v, _row=row, _p=p):
            return {_row: v[_p]}
        unit = model.units.get(ch) or model.units.get(row)         # the offset is in the channel's unit
        effects.append(Effect(name=f"offset_{ch}", equations=[row], parameters={p: 0.0}, term=term,
                              description=f"constant offset of the {ch} sensor", scale={p: 1.0},
                              units={p: unit} if unit else {}))
    return Library(name="generic", effects=effects)


def as_library(obj, model: IdentificationModel, name: str) -> Library:
    """``obj`` as a :class:`Library` named ``name``: a Library, an Effect, a list of Effects or a
    function of the model returning one of these."""
    if isinstance(obj, Library):
        return obj
    if isinstance(obj, Effect):
        return Library(name=name, effects=[obj])
    if isinstance(obj, (list, tuple)) and all(isinstance(e, Effect) for e in obj):
        return Library(name=name, effects=list(obj))
    if callable(obj):
        return as_library(obj(model), model, name)
    raise ValueError(f"{name}: not a Library, a list of Effects or a function returning one")


def library_for(model: IdentificationModel, data=None) -> Library:
    """The candidate library of a model: ``model.settings.diagnosis_library`` if set, else the
    mechanical library of a model that declares its mechanics
    (:func:`shootlab.diagnosis.mechanical.mechanical_library`; ``data`` sets the friction laws'
    velocity scale), else the installed one for its name (or the name's prefix before '['; entry
    points ``shootlab.libraries``), else :func:`generic_library`."""
    own = model.settings.diagnosis_library
    if own is not None:
        return as_library(own, model, f"{model.name} (model settings)")
    if model.settings.mechanics is not None:
        return mechanical_library(model, data)
    base = (model.settings.nominal_model or model.name).split("[")[0]
    ep = registry.find("libraries", base)
    if ep is not None:
        return as_library(registry.load("libraries", base), model, ep.value)
    return generic_library(model)


def resolve_library(spec: str, model: IdentificationModel) -> Library:
    """A library from ``path/to/file.py:object`` / ``package.module:object`` (a Library, a list of
    Effects, or a function of the model returning one)."""
    from shootlab.estimation.lookup import load_object
    return as_library(load_object(spec), model, spec)
