"""Sim-to-real gap diagnosis (docs/design.md §4; ``docs/diagnosis.md``): where the residual is, which effect
explains it, and how far adding that effect shrinks the misfit.  Generic over any
:class:`~shootlab.estimation.IdentificationModel`.  One module per step:

======================  ==========================================================================
:mod:`.effects`         candidate effects (:class:`Effect`: a term added to some rows), their libraries
:mod:`.floor`           the noise floor: the model re-estimated on a surrogate record it fits exactly; the
                        validation record's evidence against the same floor
:mod:`.noise`           the measurement noise's colour (white + AR(1)) that the floor's surrogates are drawn with
:mod:`.where`           where: per-row residual energy against the floor, F test, time windows
:mod:`.numerics`        numerical causes first: twice the shooting points, the model's declared refinement
:mod:`.screening`       which, first: the candidate's term fitted to the residual (the screening regression)
:mod:`.which`           which: scoring by linearised re-estimation, pairs, polish, selection
:mod:`.confirmation`    the leading candidates re-estimated in full, measured on the validation record
:mod:`.shrinkage`       how far it shrinks: J and the validation free-run misfit before/after
:mod:`.pipeline`        :func:`diagnose`: the steps in turn, validation confirmation, nested models
:mod:`.verdicts`        the verdict in words: which record carried the evidence, with its figures
:mod:`.outcome`         :class:`Diagnosis`, its :class:`Status` and JSON
:mod:`.report`          ``diagnosis.json`` and ``report.md``; :mod:`.plots` the figures
:mod:`.progress`        the progress lines (one per step and per fit), messages summarised in words
:mod:`.cli`             ``shootlab diagnose``
======================  ==========================================================================

Model composition (:func:`extend`) lives in :mod:`shootlab.diagnosis.composition`, the estimation strategies
(:func:`default_estimator`, :func:`weight_continuation_estimator`, :func:`one_step`) in
:mod:`shootlab.diagnosis.estimators` and the noise level in :func:`shootlab.estimation.data.noise_level`; they are re-exported here.
Candidate libraries: the installed ones (entry points ``shootlab.libraries``), or the user's own.
"""
from __future__ import annotations

from .composition import Vars, extend
from .estimators import default_estimator, one_step, weight_continuation_estimator
from shootlab.estimation.data import noise_level
from .effects import Effect, Library
from .libraries import generic_library, library_for, resolve_library
from .floor import surrogate_data
from .numerics import numerical_check
from .outcome import Diagnosis, Status
from .pipeline import NESTED_ALPHA, diagnose
from .report import write_report
from .shrinkage import free_run_error, shrink
from .where import effective_samples, locate
from .selection import Candidate
from .which import rank

__all__ = ["Effect", "Library", "Vars", "extend", "noise_level", "surrogate_data", "locate", "rank",
           "shrink", "diagnose", "Diagnosis", "Status", "write_report", "generic_library", "library_for",
           "default_estimator", "weight_continuation_estimator", "resolve_library", "free_run_error",
           "Candidate", "one_step", "effective_samples", "NESTED_ALPHA",
           "numerical_check"]
