"""The diagnosis's report (``docs/diagnosis.md``): ``diagnosis.json``, ``report.md`` and the figures
(:mod:`.plots`), written together or not at all.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .design import separation_power, separable
from .outcome import Diagnosis, fmt
from .noise import NoiseShape
from .plots import figures
from .progress import brief

__all__ = ["write_report"]


def write_report(diag: Diagnosis, out: str | Path, plots: bool = True) -> dict:
    """``diagnosis.json``, ``report.md`` and the figures, written to a temporary folder next to
    ``out`` and moved into ``out`` only when all are complete (an interrupted run leaves nothing
    that looks like a result)."""
    from shootlab.outputs import staged_folder

    with staged_folder(out, "diagnose") as tmp:
        info = diag.to_dict()
        drawn = figures(diag, tmp) if plots else []
        info["figures"] = drawn
        (tmp / "report.md").write_text(_markdown(info))
        (tmp / "diagnosis.json").write_text(json.dumps(info, indent=2))
    return info


def _markdown(info: dict) -> str:
    """``report.md`` from the JSON of ``diagnosis.json``."""
    L = [f"# Diagnosis of `{info['model']}`", "", f"**{info['verdict']}**", ""]
    nom, ext = info["nominal"], info["extended"]
    units = info.get("units") or {}
    L.append(f"Nominal estimate: J = {fmt(nom['J'], '.5g')}, " + _values(nom["parameters"], units, ".5g"))
    if ext and ext.get("effects"):
        fit = (f"output error, cost {fmt(ext['cost'], '.5g')}" if ext.get("method") == "output-error"
               else f"J = {fmt(ext['J'], '.5g')}")
        L.append(f"\nExtended ({ext['model']}): {fit}, " + _values(ext["parameters"], units, ".5g"))
    L += _evidence_section(info)
    L += _numerics_section(info.get("numerical"))
    L += _free_run_section(info.get("free_run"))
    L += ["", "## Where", "", "| residual | share of J | rms / floor rms | p | significant | windows |", "|---|---|---|---|---|---|"]
    for w in info["where"]:
        if w["share"] is not None and w["share"] < 0.001 and not w["significant"]:
            continue
        wins = ", ".join(f"[{a:.3g}, {b:.3g}]" for a, b in w["windows"][:4]) + (" …" if len(w["windows"]) > 4 else "")
        ratio = w.get("ratio")
        L.append(f"| {w['equation']} | {100 * w['share']:.1f} % | {fmt(math.sqrt(ratio) if ratio else None)} | "
                 f"{fmt(w.get('p_value'), '.2g')} | {'yes' if w['significant'] else 'no'} | {wins} |")
    L += _which_section(info, units)
    sh = info.get("shrink")
    if sh:
        L += ["", "## How far it shrinks", "", "| measure | before | after | shrink |", "|---|---|---|---|"]
        idn = sh.get("identification")
        if idn:
            L.append(f"| J (identification) | {fmt(idn['before'])} | {fmt(idn['after'])} | {fmt(idn['shrink'], '.2f')} |")
            for r, d in idn["per_channel"].items():
                L.append(f"| residual energy {r} | {fmt(d['before'])} | {fmt(d['after'])} | {fmt(d['shrink'], '.2f')} |")
        val = sh.get("validation")
        if val:
            how = (f"simulations restarted on {fmt(val.get('window'))} windows" if val.get("measure") == "windows"
                   else "free run")
            L.append(f"| validation misfit, {how} (relative RMS) | {fmt(val['before'])} | {fmt(val['after'])} | "
                     f"{fmt(val['shrink'], '.2f')} |")
            L.append(f"| — above the noise | {fmt(val.get('before_above_noise'))} | {fmt(val.get('after_above_noise'))} | "
                     f"{fmt(val.get('shrink_above_noise'), '.2f')} |")
            for ch, d in val["per_channel"].items():
                L.append(f"| validation RMS {ch} | {fmt(d['before'])} | {fmt(d['after'])} | {fmt(d['shrink'], '.2f')} |")
    if info.get("notes"):
        L += ["", "## Notes", ""] + [f"- {_note(n)}" for n in info["notes"]]
    if info.get("figures"):
        L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in info["figures"]]
    return "\n".join(L) + "\n"


def _evidence_section(info: dict) -> list[str]:
    """Which record carries the evidence of a structural error: J against the noise floor's on the
    identification record, the validation misfit in units of the noise against the floor's
    (:func:`.floor.validation_evidence`)."""
    ev, floor, nom = info.get("evidence"), info.get("floor") or {}, info.get("nominal") or {}
    if not ev:
        return []
    ident = any(w["significant"] for w in info.get("where", []))
    how = ("simulations restarted on windows" if ev.get("measure") == "windows" else "free run")
    return ["", "## Evidence", "", "| record | measure | nominal model | noise floor | significant |", "|---|---|---|---|---|",
            f"| identification | J | {fmt(nom.get('J'), '.4g')} | {fmt(floor.get('J'), '.4g')} | {'yes' if ident else 'no'} |",
            f"| validation | {how}: RMS misfit / noise | {fmt(ev.get('misfit'))} | {fmt(ev.get('floor_misfit'))} | "
            f"{'yes' if ev.get('significant') else 'no'} (ratio {fmt(ev.get('ratio'))}, p = {fmt(ev.get('p_value'), '.2g')}) |"
            ] + [f"\nThe noise on {c} is not white Gaussian: "
                 f"{NoiseShape(sh['pole'], sh['white'], sh.get('tails', 1.0)).describe()}; "
                 "the floors' surrogates are drawn with it." for c, sh in (floor.get("noise_shapes") or {}).items()]


def _numerics_section(num: dict | None) -> list[str]:
    """The numerical checks (:mod:`.numerics`) as a table: J and the free-run misfit per model and grid."""
    if not num:
        return []
    L = ["", "## Numerical checks", "", "| model | shooting points | J | free-run misfit above the noise (× noise) |",
         "|---|---|---|---|"]
    pc, rc = num.get("points") or {}, num.get("refinement") or {}
    rows = [rc.get("before") or pc.get("before"), pc.get("after"), *rc.get("steps", [])]
    for s in (r for r in rows if r):
        L.append(f"| {s['model']} | {s['points']} | {fmt(s['J'], '.5g')} | {fmt((s.get('misfit') or {}).get('overall'))} |")
    return L


def _free_run_section(fr: dict | None) -> list[str]:
    """The free-run screen (:mod:`.free_run_screen`): refinements and candidates by their validation shrink."""
    if not fr:
        return []
    fits = ("the TPBVP's full re-estimate" if fr.get("method") == "re-estimates" else "output error")
    L = ["", "## The free run on the validation record", "", fr.get("verdict", ""), "",
         f"| model / candidate | fit ({fits}) | validation cost shrink |", "|---|---|---|"]
    for r in fr.get("refinements", []):
        L.append(f"| {r['model']} (refinement) | {'converged' if r['success'] else 'failed'} | {fmt(r['shrink'], '.3f')} |")
    for c in fr.get("candidates", []):
        L.append(f"| + {c['effect']} | {'converged' if c.get('success') else 'not converged: ' + brief(c.get('message', ''))} | "
                 f"{fmt(c.get('validation_shrink'), '.3f')} |")
    return L


#: a note longer than this is shown by its first sentence (the whole of it is in ``diagnosis.json``)
NOTE_LENGTH = 240


def _note(note: str) -> str:
    """A note of ``report.md``: as it is, or its first sentence when longer than :data:`NOTE_LENGTH`
    (a solver's message with its advice)."""
    return note if len(note) <= NOTE_LENGTH else f"{brief(note)} (in full: `notes` in diagnosis.json)"


def _values(parameters: dict, units: dict, spec: str = ".4g") -> str:
    """``p = v [unit]`` for each parameter, with the unit where the model or the effect declares one."""
    return ", ".join(f"{k} = {fmt(v, spec)}" + (f" [{units[k]}]" if units.get(k) else "") for k, v in parameters.items())


def _which_section(info: dict, units: dict, rows: int = 8) -> list[str]:
    """The ranking of the single effects, the selected ones marked, and the selection with the figures
    its verdict rests on: the confidence of :attr:`.outcome.Diagnosis.confidence` and, for the
    TPBVP's selection, J of the full re-estimate."""
    selected = list(info.get("selected") or [])
    nom = info.get("nominal") or {}
    L = ["", "## Which", "", "| effect | explains alone | confidence | parameters alone |", "|---|---|---|---|"]
    ranking = info.get("ranking") or []
    shown = ranking[:rows] + [r for r in ranking[rows:] if r["effect"] in selected]
    for r in shown:
        mark = " **(selected)**" if r["effect"] in selected else ""
        J = r.get("J")
        if r.get("failed"):
            explains = "its full re-estimate did not converge: " + brief(r["failed"])
        elif J is None:
            explains = "not converged: " + brief(r.get("why") or "no re-estimate")
        else:
            explains = f"{100 * r['score']:.1f} %" + (" (in full" + (
                f"; one step: {100 * (1 - r['linearised'] / nom['J']):.1f} %" if r.get("linearised") is not None
                and nom.get("J") and math.isfinite(r["linearised"]) else "") + (
                f"; validation cost {100 * r['validation_shrink']:+.0f} %" if r.get("validation_shrink") is not None
                else "") + ")" if r.get("full") else "")
        conf = r.get("confidence_nested", r.get("confidence"))
        L.append(f"| {r['effect']}{mark} | {explains} | {fmt(conf, '.2f')} | {_values(r['parameters'], units)} |")
    if ranking:
        L += ["", "*explains alone*: 1 − J/J_nominal after the effect's own linearised re-estimation, or its full "
              "re-estimation where marked *in full* (the leading candidates, and those whose one step cannot be "
              "trusted); *confidence*: the posterior weight (BIC weights on the residual's effective sample size over "
              "no effect, single effects and pairs, times the validation record's likelihood where it was measured) "
              "of the models that contain the effect, itself or through a richer effect that nests it (Stribeck "
              "friction contains Coulomb friction)."]
    skipped = info.get("skipped_effects") or {}
    if skipped:
        L += ["", "Not compared:", ""] + [f"- {n}: {why}" for n, why in skipped.items()]
    ext, nom = info.get("extended") or {}, info.get("nominal") or {}
    line = f"\nSelected: {' + '.join(selected) or 'none'}"
    if selected:
        line += f", confidence {fmt(info.get('confidence'), '.2f')}"
        if (info.get("free_run") or {}).get("selected"):
            line += (" (the weight of the ranking on the validation record, which decided: below)"
                     if info["free_run"].get("method") == "re-estimates" else
                     " (the free-run screen's weight: it decided, below the TPBVP's ranking above)")
        elif ext.get("J") is not None and nom.get("J"):
            line += (f"; re-estimated in full with them, J {fmt(nom['J'], '.4g')} → {fmt(ext['J'], '.4g')} "
                     f"({100 * (1 - ext['J'] / nom['J']):.1f} % less)")
    L.append(line)
    L += _lookalike_lines(info.get("discrimination"), selected)
    return L


def _lookalike_lines(d: dict | None, selected: list[str]) -> list[str]:
    """The look-alikes of the selection with their weights, the validation evidence on them and the
    proposed experiment (:func:`.lookalikes.discriminate`)."""
    if not d or not (d.get("rivals") or d.get("switch")):
        return []
    L = []
    sw = d.get("switch")
    if sw:
        L.append(f"\nThe validation record changed the selection from {' + '.join(sw['replaced'])} to "
                 f"{' + '.join(selected)} (alike on the identification record).")
    if d.get("rivals"):
        L += ["", f"Rivals of the selection — a look-alike when its models weigh at least "
                  f"{fmt(d.get('threshold'), '.3g')} of the selection's, or when the difference ΔC of the free-run "
                  f"costs (its own minus the selection's, both records) is below {fmt(d.get('threshold_z'), '.3g')} "
                  f"standard errors (z), or the separation S of the two free runs on the records is below "
                  f"{fmt(d.get('threshold_z'), '.3g')} times its spread s = max(2√S, se) (Φ(S/s): the best the records "
                  f"could tell them apart):",
              "", "| rival | its model | weight | of the selection's | validation cost Σ((y − z)/σ)² | ΔC ± se | z | "
              "S | Φ(S/s) | look-alike |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in d["rivals"]:
            dc = (f"{fmt(r['cost_difference'], '+.4g')} ± {fmt(r['standard_error'], '.3g')}"
                  if r.get("cost_difference") is not None else "–")
            L.append(f"| {r['effect']} | {' + '.join(r['effects'])} | {fmt(r['weight'], '.3g')} | "
                     f"{fmt(r['ratio'], '.3g')} | {fmt(r.get('validation_cost'), '.5g')} | {dc} | "
                     f"{fmt(r.get('z'), '.3g')} | {fmt(r.get('separation'), '.4g')} | {fmt(r.get('power'), '.3g')} | "
                     f"{'yes' if r.get('lookalike') else 'no'} |")
    ex = d.get("experiment")
    if ex and not separable(ex):
        L += ["", f"**No discriminating experiment**: no input of the family separates the free runs of "
                  f"{' + '.join(ex['between'][0])} and {' + '.join(ex['between'][1])} by a noise unit (at most "
                  f"{fmt(ex['separation'], '.3g')}): with these estimates the two predict the same."]
    elif ex:
        inp = ex["input"]
        L += ["", f"**Proposed experiment**: {inp['label']} — predicted separation of the free runs of "
                  f"{' + '.join(ex['between'][0])} and {' + '.join(ex['between'][1])}: {fmt(ex['separation'], '.4g')} "
                  f"noise units (Σ((y₁ − y₂)/σ)² over the measured channels; under the identification input "
                  f"{fmt(ex.get('separation_identification'), '.3g')}); on white noise a record under it gives the "
                  f"right model the lower cost with probability {separation_power(ex['separation']):.2f}.  "
                  f"`shootlab diagnose … --design FILE` writes it; diagnose again with its record as `--validate`."]
    return L
