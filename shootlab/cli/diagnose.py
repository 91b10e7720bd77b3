"""``shootlab diagnose`` (``docs/diagnosis.md``; the arguments are declared in :mod:`shootlab.cli`):
the model, the records and the library resolved and checked before any work, then
:func:`shootlab.diagnosis.diagnose` and :func:`shootlab.diagnosis.write_report`.  Exit status 0
for a verdict the diagnosis stands by, 1 otherwise (:attr:`shootlab.diagnosis.outcome.Status.definite`).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import ModuleType

from shootlab import registry
from shootlab.diagnosis.libraries import as_library, library_for, resolve_library
from shootlab.diagnosis.pipeline import diagnose
from shootlab.diagnosis.report import write_report

__all__ = ["run_cli", "module_of"]


def module_of(spec: str) -> ModuleType | None:
    """The module an import spec's object lives in (already imported by :func:`resolve_model`)."""
    import importlib
    import sys as _sys

    ep = registry.find("models", spec)
    target, sep, _ = (ep.value if ep else spec).rpartition(":")
    if not sep:
        return None
    if target.endswith(".py") or "/" in target or "\\" in target:
        path = Path(target).resolve()
        for mod in list(_sys.modules.values()):
            f = getattr(mod, "__file__", None)
            if f and Path(f).resolve() == path:
                return mod
        return None
    try:
        return importlib.import_module(target)
    except Exception:  # noqa: BLE001
        return None


def run_cli(args) -> int:
    """``shootlab diagnose``: every input is checked before any work; the output folder receives
    the results only when the diagnosis is complete (:func:`write_report`).  Progress on standard
    output: a line per step and per fit; ``--verbose`` adds every Newton iteration, ``--quiet``
    prints only the verdict."""
    from shootlab.bvp.device import resolve_device
    from shootlab.estimation.lookup import resolve_model
    from shootlab.diagnosis.design import write_input
    from shootlab.diagnosis.design import separation_power, separable
    from shootlab.outputs import check_output_file, check_output_folder
    from .arguments import load_data, parse_assignments, parse_initial, solver_flags

    say = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    check_output_folder(args.out, force=getattr(args, "force", False),
                        inputs={"--data": args.data, "--validate": args.validate})
    design = getattr(args, "design", None)
    if design:
        check_output_file(design)
        if Path(design).resolve() in {Path(p).resolve() for p in (args.data, args.validate) if p}:
            raise ValueError(f"--design {design} is an input of this diagnosis; give another file name")
    device = resolve_device(getattr(args, "device", None))
    model = resolve_model(args.model, parse_assignments(args.option, "--option"))
    initial = parse_initial(getattr(args, "initial", None), model)
    points = getattr(args, "points", None)
    if initial or points:
        model = replace(model, prior=dict(model.prior, **initial),
                        settings=model.settings.replace(points=points) if points else model.settings)
    # the solver flags and --no-fallback hold for every estimate of the diagnosis, through the
    # model's settings (an extended model inherits them); its one-step re-estimates stay one undamped step
    settings = model.settings.replace(solver=solver_flags(args, model))
    if args.no_fallback:
        settings = settings.replace(fallback=False)
    model = replace(model, settings=settings)
    data = load_data(args.data, needed=model.measured, inputs=model.given)
    validation = None
    if args.validate:
        try:
            validation = load_data(args.validate, "--validate", needed=model.measured, inputs=model.given)
        except ValueError as exc:
            raise ValueError(f"validation data {args.validate}: {exc}") from None
    if args.library:
        library = resolve_library(args.library, model)
    else:
        mod = module_of(args.model)
        own = getattr(mod, "diagnosis_library", None) if mod is not None else None
        library = as_library(own, model, f"{args.model} (diagnosis_library)") if own is not None else library_for(model, data)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
    say(f"diagnosing {model.name} on {args.data} ({data.t.size} samples) with the library {library.name!r}: "
        + ", ".join(library.names))
    diag = diagnose(model, data, library, validation=validation, effects=effects, seed=args.seed,
                    log=None if args.quiet else say, progress=not args.quiet,
                    verbose=bool(getattr(args, "verbose", False)) and not args.quiet, device=device)
    info = write_report(diag, args.out, plots=not args.no_plots)
    print(diag.verdict)
    if design:
        told = diag.discrimination or {}
        ex = told.get("experiment")
        if ex is None and told.get("propose") is not None:      # no look-alike: against the heaviest rival
            ex = told["propose"]()
        if ex is not None and not separable(ex):
            print(f"--design: no input of the family separates the two free runs by a noise unit (at most "
                  f"{ex['separation']:.3g}); {design} not written")
        elif ex is not None:
            write_input(design, ex)
            print(f"wrote {design}: {ex['input']['label']} ({len(ex['t'])} samples of t, {', '.join(ex['values'])}); "
                  f"predicted separation of {' + '.join(ex['between'][0])} and {' + '.join(ex['between'][1])}: "
                  f"{ex['separation']:.3g} noise units (under the identification input "
                  f"{ex['separation_identification']:.3g}; right with probability {separation_power(ex['separation']):.2f})")
        else:
            why = ("no rival of the selection is near enough to compare" if not told.get("rivals") else
                   "no input of the family keeps both free runs within the records' range")
            print(f"--design: no experiment proposed ({why}); {design} not written")
    print(f"status: {diag.status.value}; selected: {', '.join(diag.selected) or 'none'}; wrote "
          f"{Path(args.out) / 'diagnosis.json'}, report.md"
          + (", " + ", ".join(info.get("figures", [])) if info.get("figures") else ""))
    return 0 if diag.success else 1
