"""The diagnosis's report (``docs/diagnosis.md``): ``diagnosis.json``, ``report.md`` and the figures
(:mod:`.plots`), written together or not at all.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .outcome import Diagnosis, fmt
from .plots import figures

__all__ = ["write_report"]


def write_report(diag: Diagnosis, out: str | Path, plots: bool = True) -> dict:
    """``diagnosis.json``, ``report.md`` and the figures, written to a temporary folder next to
    ``out`` and moved into ``out`` only when all are complete (an interrupted run leaves nothing
    that looks like a result)."""
    from ..outputs import staged_folder

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
    L.append(f"Nominal estimate: J = {fmt(nom['J'], '.5g')}, " + ", ".join(f"{k} = {fmt(v, '.5g')}" for k, v in nom["parameters"].items()))
    if ext and ext.get("effects"):
        fit = (f"output error, cost {fmt(ext['cost'], '.5g')}" if ext.get("method") == "output-error"
               else f"J = {fmt(ext['J'], '.5g')}")
        L.append(f"\nExtended ({ext['model']}): {fit}, " + ", ".join(f"{k} = {fmt(v, '.5g')}" for k, v in ext["parameters"].items()))
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
    L += ["", "## Which", "", "| effect | explains | confidence | parameters |", "|---|---|---|---|"]
    for r in info["ranking"][:8]:
        L.append(f"| {r['effect']} | {100 * r['score']:.1f} % | {r['confidence']:.2f} | "
                 + ", ".join(f"{k} = {fmt(v, '.4g')}" for k, v in r["parameters"].items()) + " |")
    skipped = info.get("skipped_effects") or {}
    if skipped:
        L += ["", "Not compared:", ""] + [f"- {n}: {why}" for n, why in skipped.items()]
    L.append(f"\nSelected: {', '.join(info['selected']) or 'none'}")
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
        L += ["", "## Notes", ""] + [f"- {n}" for n in info["notes"]]
    if info.get("figures"):
        L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in info["figures"]]
    return "\n".join(L) + "\n"


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
    L = ["", "## The free run on the validation record", "", fr.get("verdict", ""), "",
         "| model / candidate | fit | validation cost shrink |", "|---|---|---|"]
    for r in fr.get("refinements", []):
        L.append(f"| {r['model']} (refinement) | {'converged' if r['success'] else 'failed'} | {fmt(r['shrink'], '.3f')} |")
    for c in fr.get("candidates", []):
        L.append(f"| + {c['effect']} | {'converged' if c.get('success') else 'failed: ' + str(c.get('message', ''))[:60]} | "
                 f"{fmt(c.get('validation_shrink'), '.3f')} |")
    return L
