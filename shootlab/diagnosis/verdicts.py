"""The verdict in words (``docs/diagnosis.md``): which record carried the evidence of a structural
error and with which figures (:func:`evidence_words`), the verdicts without one
(:func:`no_error_words`) or without an explanation (:func:`unexplained_words`), and how a
validation misfit was measured (:func:`measure_words`, :func:`evidence_measure`).
"""
from __future__ import annotations

import math
from typing import Sequence

from .confirmation import failures
from .floor import NoiseFloor, beyond_floor
from .outcome import fmt
from .selection import Candidate

__all__ = ["evidence_measure", "evidence_words", "no_error_words", "unexplained_words", "measure_words"]


def evidence_measure(evidence: dict) -> str:
    """The validation measure of :func:`.floor.validation_evidence` in words."""
    if evidence["measure"] == "windows":
        return f"misfit of simulations restarted every {evidence['window']:.3g}"
    if evidence["measure"] == "fitted_start":
        return "free-run misfit (from a fitted start)"
    return "free-run misfit (from the record's start)"


def evidence_words(on_identification: bool, J: float, floor: NoiseFloor | None, evidence: dict,
                   after: float | None = None, selected: Sequence[str] = (), left: dict | None = None) -> str:
    """Which record carried the evidence of a structural error, with its figures; ``after``: the
    validation cost of the model extended with ``selected``, by the same measure; ``left``: what
    that model leaves there against its own noise floor (:func:`.floor.left_by`; without it the
    nominal model's floor judges)."""
    val = (f"the validation {evidence_measure(evidence)} {fmt(evidence['misfit'])}× the noise "
           f"({fmt(evidence['floor_misfit'])}× on the noise floor"
           + (f"; {fmt(math.sqrt(after / evidence['samples']))}× with {' + '.join(selected)}"
              if after is not None and evidence["samples"] and math.isfinite(after) else "") + ")")
    if after is not None and evidence["samples"] and math.isfinite(after) and beyond_floor(after, evidence)[2]:
        what = ' + '.join(selected)
        if left is None:
            val += f"; what {what} leaves there is more than the noise explains: part of the error is not explained"
        else:       # the answer's own free run may not drift where the nominal one does: its measure
            own = (f"{fmt(left['misfit'])}× the noise" + (f" by the {evidence_measure(left)}" if left["measure"]
                                                          != evidence["measure"] else "")
                   + f", {fmt(left['floor_misfit'])}× on its own noise floor")
            val += (f"; what {what} leaves there is more than the noise and the estimate of its parameters explain "
                    f"({own}): part of the error is not explained" if left["significant"] else
                    f"; what {what} leaves there is what the noise and the estimate of its parameters leave ({own})")
    ident = f"J {J:.4g} against the floor's {floor.J:.4g}" if floor is not None else f"J {J:.4g}, no floor"
    if on_identification and evidence["significant"]:
        return f"significant on both records: {ident}; {val}"
    if on_identification:
        return f"significant on the identification record ({ident}); {val}, within what the noise explains"
    return (f"significant on the validation record: {val}; the identification residual is at its floor "
            f"({ident})")


def no_error_words(J: float, floor: NoiseFloor | None, evidence: dict | None) -> str:
    """The verdict without a significant misfit on either record."""
    out = "no significant structural error: the residual is at the noise floor" + (
        f" (J {J:.4g} against {floor.J:.4g})" if floor is not None else "")
    if evidence is not None:
        out += (f" and the validation {evidence_measure(evidence)} within what the noise explains "
                f"({fmt(evidence['misfit'])}× the noise, {fmt(evidence['floor_misfit'])}× on the noise floor)")
    return out


def unexplained_words(verdict: str, lead: Sequence[Candidate]) -> str:
    """An ``unexplained`` verdict with what the leading candidates' full re-estimates gave."""
    done = [f"{c.label} {100 * max(c.explained_excess, 0.0):.0f} %" + (
        f" (validation cost {100 * c.validation_shrink:+.0f} %)" if c.validation_shrink is not None else "")
        for c in lead if c.full and math.isfinite(c.J)]
    failed = failures(lead)
    if done:
        verdict += f"; re-estimated in full: {', '.join(done)}"
    if failed:
        verdict += f"; could not be estimated: {', '.join(failed)}"
    return verdict


def measure_words(val: dict) -> str:
    """How the validation misfit was measured, in words (:func:`.shrinkage.validation_summary`)."""
    if val.get("measure") == "windows":
        return (f"misfit of simulations restarted every {val['window']:.3g} (the free run drifts: "
                f"{val['free_run']['before']:.3g} channel std)")
    return "free-run misfit (from the record's start)"
