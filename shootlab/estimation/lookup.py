"""Model lookup for the command line: installed names or a user's ``file.py:object`` / ``pkg.module:object``.

Installed names are the entry points ``shootlab.models`` (:mod:`shootlab.registry`).  The object
is an :class:`~shootlab.estimation.IdentificationModel` or a callable returning one; ``options``
(``--option key=value``) are passed to the callable.
"""
from __future__ import annotations

import importlib
import inspect
import importlib.util
import sys
from pathlib import Path

from shootlab import registry
from .model import IdentificationModel


def load_object(spec: str):
    """The object named by ``package.module:object`` or ``path/to/file.py:object`` (a file is imported
    as a fresh module).  ValueError with a plain message if it cannot be found or imported."""
    target, sep, attr = spec.rpartition(":")
    if not sep or not target or not attr:
        raise ValueError(f"unknown model {spec!r}: installed models are {', '.join(registry.names('models'))}; "
                         f"or give 'path/to/file.py:object' or 'package.module:object'")
    if target.endswith(".py") or "/" in target or "\\" in target:
        path = Path(target)
        if not path.is_file():
            raise ValueError(f"model file not found: {path}")
        name = f"_shootlab_user_{abs(hash(str(path.resolve())))}"
        mspec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(mspec)
        sys.modules[name] = module
        try:
            mspec.loader.exec_module(module)
        except Exception as exc:
            sys.modules.pop(name, None)
            raise ValueError(f"model file {path} does not import: {type(exc).__name__}: {exc}") from None
    else:
        try:
            module = importlib.import_module(target)
        except Exception as exc:
            raise ValueError(f"model module {target!r} does not import: {type(exc).__name__}: {exc}") from None
    if not hasattr(module, attr):
        raise ValueError(f"model {spec!r}: {target} has no attribute {attr!r}")
    return getattr(module, attr)


def find_model(spec: str):
    """The object an installed name or an import spec names: a model or a factory of one, not called."""
    return registry.load("models", spec) if registry.find("models", spec) else load_object(spec)


def resolve_model(spec: str, options: dict | None = None) -> IdentificationModel:
    """An IdentificationModel from an installed name or an import spec (module docstring)."""
    options = dict(options or {})
    obj = find_model(spec)
    if isinstance(obj, IdentificationModel):
        if options:
            raise ValueError(f"model {spec!r} is a fixed IdentificationModel: it takes no options {sorted(options)}")
        return obj
    if not callable(obj):
        raise ValueError(f"model {spec!r} is neither an IdentificationModel nor a callable returning one")
    valid = model_options(obj)
    if valid is not None:
        for key in options:
            if key not in valid:
                raise ValueError(f"--option {key}: model {spec!r} has no option {key!r}; "
                                 f"its options are {describe_options(obj)}")
    try:
        model = obj(**options)
    except TypeError as exc:
        raise ValueError(f"model {spec!r} does not accept the options {sorted(options)}: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"--option: model {spec!r}: {exc}") from None
    if not isinstance(model, IdentificationModel):
        raise ValueError(f"model {spec!r} returned {type(model).__name__}, not an IdentificationModel")
    return model


def model_options(factory) -> list[str] | None:
    """The keyword arguments a model factory accepts (None: any, it takes ``**kwargs``)."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return [p.name for p in params if p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)]




def describe_options(obj) -> str:
    """The options of a model factory as ``name=default`` (``name`` for one without a default),
    comma-separated, a default longer than 24 characters as its type and length (``<tuple of 5>``); ``(none)`` for a fixed model or a
    factory without keyword arguments, ``any keyword arguments`` for one that takes ``**kwargs``."""
    if isinstance(obj, IdentificationModel):
        return "(none: a fixed IdentificationModel)"
    names = model_options(obj)
    if names is None:
        return "any keyword arguments"
    params = inspect.signature(obj).parameters
    out = []
    for name in names:
        default = params[name].default
        if default is inspect.Parameter.empty:
            out.append(name)
            continue
        text = repr(default)
        if len(text) > 24:
            text = f"<{type(default).__name__} of {len(default)}>" if hasattr(default, "__len__") else text[:23] + "…"
        out.append(f"{name}={text}")
    return ", ".join(out) or "(none)"
