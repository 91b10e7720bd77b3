"""What a verdict says about its look-alikes (``docs/diagnosis.md``, "Confidence and look-alikes"):
:func:`words` makes the clause of :func:`.lookalikes.discriminate`'s result — a selection the
records changed, the look-alikes that remain and the confidence they leave, the weighing by output
error, the proposed experiment — and two caps remake it where the answer may stand in for an effect
outside the library: :func:`misfit_left` (it leaves the validation misfit beyond the noise) and
:func:`stand_in` (its estimate is not physical), both at :data:`UNRESOLVED` at most.
"""
from __future__ import annotations

import math
from typing import Sequence

from .design import separable, separation_power
from .nested import RICHER_Z, decided
from .selection import LOOK_ALIKE_Z

__all__ = ["words", "misfit_left", "stand_in", "stand_in_words", "UNRESOLVED"]


#: the confidence of a selection that leaves the validation misfit beyond what the noise explains
#: (:func:`misfit_left`), whose estimate is not physical (:func:`stand_in`), or beside a richer form of it
#: that no start could estimate (:func:`.lookalikes.discriminate`): even odds at most
UNRESOLVED = 0.5


def misfit_left(told: dict | None, selected: Sequence[str], left: str | None) -> None:
    """A selection that leaves a validation misfit beyond what the noise explains (``left``: that
    misfit in words; None when it is at its floor).  The weights compare the library's models as
    if one of them were the truth, and the validation record says none is: an effect outside the
    library remains, and the selection may stand in for it (a Stribeck law fitted to a quadratic
    drag, an input offset to a sensor's) — the confidence is at most :data:`UNRESOLVED`.  In
    place; the words are made again (a richer form of the selection that could not be estimated,
    ``told["unresolved"]``, which :func:`.lookalikes.discriminate` has named beside it, is said with the misfit)."""
    if not told or left is None:
        return
    told["unexplained"] = left
    _at_even_odds(told, selected)


def stand_in(told: dict | None, selected: Sequence[str], odd: Sequence[str]) -> None:
    """A selection whose estimate is not physical (``odd``: the ways, :func:`.effects.unphysical`)
    explains the misfit as a stand-in for an effect outside the library (Stribeck friction whose
    static level lies below its Coulomb level, for viscous friction): the confidence is at most
    :data:`UNRESOLVED`.  In place; the words are made again."""
    if not told or not odd:
        return
    told["unphysical"] = list(odd)
    _at_even_odds(told, selected)


def _at_even_odds(told: dict, selected: Sequence[str]) -> None:
    """The confidence capped at :data:`UNRESOLVED` and the words made again, in place."""
    told["confidence"] = min(told["confidence"] if told["confidence"] is not None else 1.0, UNRESOLVED)
    told["words"] = words(told, selected)


def stand_in_words(odd: Sequence[str], selected: Sequence[str], confidence: float | None = None) -> str:
    """The verdict's clause for an estimate that is not physical (``odd``); with ``confidence``,
    what the selection stands in for and the odds."""
    return f"; its estimate is not physical ({', '.join(odd)})" + (
        "" if confidence is None else
        f": {' + '.join(selected)} stands in for an effect outside the library: confidence {confidence:.2f}")


def words(told: dict, selected: Sequence[str]) -> str:
    """What a verdict adds about look-alikes: a selection the validation record changed, the
    look-alikes that remain with what makes them alike and the confidence they leave, and the
    proposed experiment."""
    text = ""
    sw = told.get("switch")
    oe = told.get("output_error")
    if sw:
        still = any(set(r["effects"]) == set(sw["replaced"]) and r["lookalike"] for r in told["rivals"])
        if sw.get("imitated"):
            old = " + ".join(sw["replaced"])
            text += (f"; {' + '.join(selected)} rather than {old}, whose estimate is not physical and takes its shape "
                     f"({', '.join(sw['imitated'])}); {old} predicts the records better by z = {sw['z']:.2g}, short "
                     f"of {RICHER_Z:.3g}: an effect outside the library may remain: confidence {told['confidence']:.2f}")
        elif sw.get("output_error"):
            text += f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}"      # the clause below says why
        elif sw.get("free_run"):
            text += (f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}, which the validation record "
                     f"alone ranked first: weighed on both records (the identification record's output-error fit "
                     f"and the validation record's free run) its weight is {sw['weight']:.2g} against "
                     f"{sw['replaced_weight']:.2g}")
        elif sw.get("simpler"):
            text += (f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}, which contains it: the "
                     f"identification record's likelihood ratio takes {' + '.join(sw['replaced'])}, the validation "
                     f"record {' + '.join(selected)} (weight {sw['weight']:.2g} against {sw['replaced_weight']:.2g}): "
                     f"confidence {told['confidence']:.2f}")
        else:
            text += (f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}, alike on the identification "
                     f"record: " + ("with the validation record its weight is " if still else
                                    "the validation record tells them apart (weight ")
                     + f"{sw['weight']:.2g} against {sw['replaced_weight']:.2g}" + ("" if still else ")"))
    alike = [r for r in told["rivals"] if r["lookalike"]]
    if alike:
        why = []
        for r in alike:
            bits = [f"its models weigh {r['ratio']:.2g} of the selection's"]
            if r.get("z") is not None:
                bits.append(f"their free-run costs differ by {r['cost_difference']:+.3g} ± {r['standard_error']:.2g} "
                            f"(z = {r['z']:.2g}), their free runs by {r['separation']:.3g} noise units")
            why.append(f"{r['effect']} ({', '.join(bits)})")
        text += (f"; look-alike{'s' if len(alike) > 1 else ''}: {'; '.join(why)} — the records given cannot tell "
                 f"{'them' if len(alike) > 1 else 'it'} from {' + '.join(selected)}: confidence "
                 f"{told['confidence']:.2f}")
    compared = [r for r in told["rivals"] if not r["lookalike"] and r.get("z") is not None]
    if compared and not alike:
        r = compared[0]
        text += (f"; against the nearest rival, {r['effect']}, on the records given: free-run costs "
                 f"{r['cost_difference']:+.3g} ± {r['standard_error']:.2g} (z = {r['z']:.2g}), their free runs "
                 f"{r['separation']:.3g} noise units apart: confidence {told['confidence']:.2f}")
    if told.get("unexplained") and told.get("unresolved"):
        text += (f"; {' and '.join(told['unresolved'])}, which contain{'s' if len(told['unresolved']) == 1 else ''} "
                 f"{' + '.join(selected)}, could not be estimated, and {' + '.join(selected)} leaves "
                 f"{told['unexplained']}: confidence {told['confidence']:.2f}")
    elif told.get("unexplained"):
        text += (f"; an effect outside the library remains, and {' + '.join(selected)} may stand in for it: "
                 f"confidence {told['confidence']:.2f}")       # the misfit left is in the evidence's words
    elif told.get("unresolved"):
        text += (f"; {' and '.join(told['unresolved'])}, which contain{'s' if len(told['unresolved']) == 1 else ''} "
                 f"{' + '.join(selected)}, could not be estimated: the records have not weighed "
                 f"{'it' if len(told['unresolved']) == 1 else 'them'}: confidence {told['confidence']:.2f}")
    if oe:                          # two nested models weighed by output error (discriminate, step 5)
        rich, simple = " + ".join(oe["effects"]), " + ".join(oe["simple"])
        costs = (f"(validation free-run costs {oe['cost_richer']:.4g} and {oe['cost_simple']:.4g}, {rich} and {simple}; "
                 f"on both records z = {oe['z']:.3g})")
        clause = (f"{rich} predicts the records better than {simple}, which it contains" if oe["z"] >= RICHER_Z else
                  f"{simple} predicts the records as well as {rich}, which contains it" if decided(oe) else
                  f"{rich} ends on its bound ({', '.join(oe['on_bound'])}) and cannot show that {simple}, which it "
                  f"contains, suffices" if oe["z"] <= -LOOK_ALIKE_Z else
                  f"{rich} predicts the records better than {simple}, which it contains, but by less than "
                  f"{RICHER_Z:.3g} standard errors" if oe["z"] >= LOOK_ALIKE_Z else
                  f"{rich} and {simple}, which it contains, predict the records alike")
        text += f"; fitted alike by output error, {clause} {costs}: confidence {told['confidence']:.2f}"
    for why in told.get("not_weighed") or ():         # a look-alike left standing without its weighing
        text += f"; {why}"
    if told.get("unphysical"):      # the misfit's clause above said what it stands in for, and the odds
        text += stand_in_words(told["unphysical"], selected, None if told.get("unexplained") else told["confidence"])
    ex = told.get("experiment")
    if ex:
        S = ex.get("separation")
        if not separable(ex):
            text += (f"; no input of the family separates their free runs (at most {_number(S)} noise units, "
                     f"Σ((y₁ − y₂)/σ)²): with these estimates the two predict the same")
        else:
            runs = (f"their simulations restarted every {ex['window']:.3g}" if ex.get("measure") == "windows"
                    else "their free runs")
            text += (f"; the input that best separates them: {ex['input']['label']}, {runs} {S:.3g} noise "
                     f"units apart (Σ((y₁ − y₂)/σ)²; the identification input: "
                     f"{_number(ex['separation_identification'])}) — on white noise a record under it gives the right "
                     f"model the lower cost with probability {separation_power(S):.2f}; `--design FILE` writes it")
    return text


def _number(v) -> str:
    return f"{v:.3g}" if v is not None and math.isfinite(v) else "–"
