"""Measured time series: loading (tensors, arrays, CSV), checks and batched interpolation.

Each channel is interpolated in time by a cubic spline through its valid samples (C²,
so that high-order integrators keep their order between samples); missing samples (NaN)
are not interpolated over: the channel's *weight* ``mask(t)`` is zero on every sampling
interval that touches a missing sample, so they drop out of the cost instead of crashing it.
An input that drives a model cannot lose its weight: its short gaps are filled by linear
interpolation, its empty rows at the ends left out (:meth:`Measurements.fill_inputs`).
"""
from __future__ import annotations

import csv
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from torch import Tensor


#: the longest run of missing samples inside the record that :meth:`Measurements.fill_inputs`
#: interpolates across in an input channel: the samples on either side cannot tell what a longer
#: run hides
MAX_INPUT_GAP = 10
#: the largest estimated error of such a linear fill (:func:`fill_error`), as a fraction of the
#: channel's standard deviation, unless the channel's noise alone explains the estimate
FILL_TOL = 0.05


@dataclass
class Measurements:
    """A record: sample times and named channels, NaN marking a missing sample.

    Parameters
    ----------
    t : array_like, shape (K,)
        Sample times, finite and strictly increasing.
    channels : mapping of str to array_like
        Channel name → its K samples; NaN is a missing sample (zero weight in an estimate).
    units : dict of str to str, optional
        Column → unit, as read from a header such as ``t [s]``.
    text : dict of str to str, optional
        Non-numeric columns the reader ignored, with the reason.
    notes : list of str, optional
        What the reader did, one line each.
    source : str, optional
        The file name, for messages.
    rows : array_like of int, optional
        The file's row of each sample (the header is row 1), for messages.

    Raises
    ------
    ValueError
        Fewer than two samples, times that are not finite or not increasing (a duplicate time
        named with its rows), a channel of another length or without a valid sample, and a
        value that would wreck an estimate (:func:`suspect_value`: inf, a magnitude whose square
        overflows, an outlier a million spreads from the rest), named with its row.

    See Also
    --------
    Measurements.from_csv : read a CSV as a spreadsheet writes it.
    Measurements.coerce : a record from Measurements, a CSV path or a mapping with key ``t``.
    """

    t: np.ndarray
    channels: dict[str, np.ndarray]
    units: dict[str, str] = field(default_factory=dict)       # column -> unit from the header ("t [s]")
    text: dict[str, str] = field(default_factory=dict)        # ignored non-numeric column -> why
    notes: list[str] = field(default_factory=list)            # what the reader did (one line each)
    source: str = ""                                          # file name, for messages
    rows: np.ndarray | None = None                            # the file's row of each sample (header: row 1)

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if self.t.size < 2:
            raise ValueError(f"{self._where()}measurements need at least two samples, got {self.t.size}")
        if not np.isfinite(self.t).all():
            raise ValueError("the time column t contains NaN or inf")
        if self.rows is not None:
            self.rows = np.asarray(self.rows, dtype=np.int64).reshape(-1)
            if self.rows.size != self.t.size:
                raise ValueError(f"{self.rows.size} row numbers for {self.t.size} samples")
        if (np.diff(self.t) <= 0).any():
            i = int(np.nonzero(np.diff(self.t) <= 0)[0][0])
            if self.t[i + 1] == self.t[i]:
                raise ValueError(f"{self._where()}duplicate time stamp t = {self.t[i]:g} at "
                                 f"{self.span(i, i + 2, ' and ', times=False)}")
            raise ValueError(f"sample times must be strictly increasing: t[{i}] = {self.t[i]} >= t[{i + 1}] = {self.t[i + 1]}")
        chans = {}
        for name, v in self.channels.items():
            v = np.asarray(v, dtype=np.float64).reshape(-1)
            if v.size != self.t.size:
                raise ValueError(f"channel {name!r} has {v.size} samples but t has {self.t.size}")
            bad = suspect_value(v)
            if bad is not None:
                raise ValueError(f"{self._where()}channel {name!r} sample {bad[0]} (t = {self.t[bad[0]]:g}) {bad[1]}")
            if np.isnan(v).all():
                raise ValueError(f"channel {name!r} has no valid sample")
            chans[name] = v
        self.channels = chans

    @classmethod
    def from_csv(cls, path: str | Path) -> "Measurements":
        """Read a CSV as spreadsheets write it (:func:`read_table`)."""
        return read_table(path)

    @classmethod
    def coerce(cls, data) -> "Measurements":
        """Measurements, a CSV path, or a mapping with key 't' and channel arrays/tensors."""
        if isinstance(data, Measurements):
            return data
        if isinstance(data, (str, Path)):
            out = cls.from_csv(data)
            for note in out.notes:          # the command line prints them; here they are warnings
                warnings.warn(note, stacklevel=3)
            return out
        if isinstance(data, Mapping):
            if "t" not in data:
                raise ValueError("measurement mapping needs a key 't'")
            cols = {k: _np(v) for k, v in data.items() if k != "t"}
            return cls(_np(data["t"]), cols)
        raise ValueError(f"cannot read measurements from {type(data).__name__}")

    def to_csv(self, path: str | Path) -> None:
        """Write ``t`` and the channels as CSV (:func:`write_table`: 17 significant digits, so
        :meth:`from_csv` reads the same numbers back)."""
        write_table(path, dict(self.channels, t=self.t), ["t"] + list(self.channels))

    def _where(self) -> str:
        return f"{self.source}: " if self.source else ""

    def span(self, i: int, j: int, dash: str = "–", times: bool = True) -> str:
        """Samples ``i … j−1`` for a message: the file's rows (``rows 302–306 (t = 3 … 3.04)``) when
        the record was read from one, else the sample indices (``samples 300–304 (…)``)."""
        first, last = (int(self.rows[i]), int(self.rows[j - 1])) if self.rows is not None else (i, j - 1)
        what = "row" if self.rows is not None else "sample"
        out = f"{what} {first}" if j - i == 1 else f"{what}s {first}{dash}{last}"
        if times:
            out += f" (t = {self.t[i]:g})" if j - i == 1 else f" (t = {self.t[i]:g} … {self.t[j - 1]:g})"
        return out

    def fill_inputs(self, names, max_gap: int = MAX_INPUT_GAP, ends: str = "drop",
                    cover: tuple[float, float] | None = None) -> tuple["Measurements", list[str]]:
        """The record with the missing samples of the input channels ``names`` (the channels that
        drive a model: its ``given`` ones) made good, and one note per thing done.

        An input cannot carry zero weight where it is missing: a channel that alone determines an
        input ζ leaves it undetermined there (FᵀVF is singular) and a free run needs it at every
        time.  So

        * a run of at most ``max_gap`` missing samples inside the record is filled by linear
          interpolation between the neighbouring valid samples where its estimated error
          (:func:`fill_error`) is within :data:`FILL_TOL` of the channel's standard deviation or
          within three times the noise of that estimate (:func:`noise_level`);
        * the rows before the first and after the last row where every input is known are left
          out (``ends="drop"``; the record is shortened, those rows have no weight), or are an
          error (``ends="error"``, for a free run that must start at the first sample);
        * any other run inside the record is a ValueError naming the column and the rows, and so
          are dropped rows inside the interval ``cover`` that must stay in the record.

        Returns ``(self, [])`` when no input sample is missing."""
        if ends not in ("drop", "error"):
            raise ValueError(f"ends must be 'drop' or 'error', got {ends!r}")
        names = [n for n in dict.fromkeys(names) if n in self.channels]
        missing = {n: np.isnan(self.channels[n]) for n in names}
        if not any(m.any() for m in missing.values()):
            return self, []
        src, notes = self._where(), []
        known = ~np.logical_or.reduce(list(missing.values()))
        if known.sum() < 2:
            raise ValueError(f"{src}the input column(s) {', '.join(map(repr, names))} have fewer than two rows "
                             f"where all of them are known")
        first, last = int(np.argmax(known)), int(known.size - 1 - np.argmax(known[::-1]))
        a, b = cover if cover is not None else (math.inf, -math.inf)
        tol = 1e-12 * max(1.0, abs(self.t[0]), abs(self.t[-1]))
        for lo, hi, where, cut in ((0, first, "start", self.t[first] > a + tol),
                                   (last + 1, known.size, "end", self.t[last] < b - tol)):
            if lo == hi:
                continue
            empty = [repr(n) for n in names if missing[n][lo:hi].any()]
            cols = f"input column{'s' if len(empty) > 1 else ''} {', '.join(empty)}"
            if ends != "drop" or cut:
                inside = f", inside the interval [{a:g}, {b:g}]" if cut else ""
                raise ValueError(f"{src}{cols} is empty in {self.span(lo, hi)} at the {where} of the record"
                                 f"{inside}: the model cannot be driven there; give the input or "
                                 f"{'start later' if where == 'start' else 'end earlier'}")
            notes.append(f"{src}{self.span(lo, hi)} left out: {cols} is empty there, at the {where} of the record")
        keep = slice(first, last + 1)
        t, chans = self.t[keep], {n: v[keep] for n, v in self.channels.items()}
        out = Measurements(t, chans, units=dict(self.units), text=dict(self.text), notes=list(self.notes),
                           source=self.source, rows=None if self.rows is None else self.rows[keep])
        for n in names:
            v = out.channels[n]
            gap = np.isnan(v)
            if not gap.any():
                continue
            runs = runs_of(gap)
            spread, sigma, worst = float(np.nanstd(v)), noise_level(out, [n])[n], 0.0
            for i, j in runs:
                if j - i > max_gap:
                    raise ValueError(f"{src}input column {n!r} is empty in {out.span(i, j)}: {j - i} missing samples "
                                     f"in a row, more than the {max_gap} that are interpolated across; fill them or "
                                     f"cut the record there")
                e, gain = fill_error(t, v, i, j)
                if e > max(FILL_TOL * spread, 3.0 * gain * sigma):
                    raise ValueError(f"{src}input column {n!r} is empty in {out.span(i, j)}: a linear fill would be "
                                     f"off by about {e:.2g} there (the cubic through the samples on either side), "
                                     f"more than {FILL_TOL * spread:.2g} ({100 * FILL_TOL:g} % of the column's standard "
                                     f"deviation); fill them or cut the record there")
                worst = max(worst, e)
            out.channels[n] = linear_fill(t, v)
            where = "; ".join(out.span(i, j) for i, j in runs[:3]) + (f"; … ({len(runs)} gaps)" if len(runs) > 3 else "")
            k = int(gap.sum())
            notes.append(f"{src}{k} missing sample{'s' if k > 1 else ''} of input column {n!r} interpolated "
                         f"linearly (estimated error up to {worst:.2g}"
                         + (f", {100 * worst / spread:.2g} % of its standard deviation" if spread > 0 else "")
                         + f"): {where}")
        return out, notes

    def require(self, names, start: float, end: float) -> None:
        """ValueError unless every channel in ``names`` is numeric and the data cover [start, end]."""
        for n in names:
            if n not in self.channels and n in self.text:
                raise ValueError(f"{self._where()}column {n!r} is needed by the model but {self.text[n]}")
        missing = [n for n in names if n not in self.channels]
        if missing:
            raise ValueError(f"{self._where()}the data lack channel(s) {missing}; it has {sorted(self.channels)}")
        if self.t[0] > start + 1e-12 * max(1.0, abs(start)) or self.t[-1] < end - 1e-12 * max(1.0, abs(end)):
            raise ValueError(f"the data cover [{self.t[0]}, {self.t[-1]}], shorter than the interval [{start}, {end}]")


    def require_samples(self, model, start: float, end: float) -> None:
        """ValueError when [start, end] holds too few samples to estimate ``model``: the rule is
        at least 2 × (states + parameters) samples with a valid value of a measured (not given)
        channel — the unknowns are the initial states and the parameters."""
        names = [c for c in model.measured if c not in model.given] or list(model.measured)
        inside = (self.t >= start) & (self.t <= end)
        valid = np.zeros(self.t.size, dtype=bool)
        for c in names:
            valid |= ~np.isnan(self.channels[c])
        n = int((valid & inside).sum())
        ns, npar = len(model.states), len(model.parameters)
        need = 2 * (ns + npar)
        if n < need:
            raise ValueError(f"{self._where()}too few samples for {npar} parameters: {n} sample(s) of "
                             f"{', '.join(names)}; model {model.name!r} needs at least 2 x ({ns} states + "
                             f"{npar} parameters) = {need}")


def with_filled_inputs(data: Measurements, names, cover: tuple[float, float] | None = None,
                       ends: str = "drop") -> Measurements:
    """:meth:`Measurements.fill_inputs` of the channels ``names``, its notes given as warnings (the
    command line fills the inputs when it reads the file and prints them there)."""
    out, notes = data.fill_inputs(names, ends=ends, cover=cover)
    for note in notes:
        warnings.warn(note, stacklevel=3)
    return out


def linear_fill(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` (K,) with its missing samples (NaN) replaced by linear interpolation in ``t`` between
    the neighbouring valid samples, and by the nearest valid sample before the first and after
    the last; ``v`` itself when none is missing."""
    ok = ~np.isnan(v)
    return v if ok.all() else np.interp(t, t[ok], v[ok])


def fill_error(t: np.ndarray, v: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """The error of the linear fill of the missing samples ``v[i:j]`` (between the valid samples
    ``i − 1`` and ``j``), estimated as the largest difference on them between the polynomial
    through the two valid samples on either side (a cubic; a quadratic next to the record's end)
    and that line: for a smooth signal the line's error is h²/8 |v''| over the run's length h, and
    the estimate is off by the cubic's own error, O(h⁴ |v⁗|).  Returns ``(estimate, gain)``:
    ``gain`` is the largest norm of the estimate's weights on those samples, so white noise of
    std σ in them alone gives an estimate of std ``gain · σ``.  ``(0, 0)`` where only the two
    neighbours are valid."""
    ok = ~np.isnan(v)
    before, after = np.nonzero(ok[:i])[0][-2:], i + np.nonzero(ok[i:])[0][:2]
    nodes = np.concatenate([before, after])
    if nodes.size < 3:
        return 0.0, 0.0
    x, tq = t[nodes], t[i:j]
    w = np.ones((tq.size, nodes.size))                 # Lagrange basis at the missing samples
    for k in range(nodes.size):
        for m in range(nodes.size):
            if m != k:
                w[:, k] *= (tq - x[m]) / (x[k] - x[m])
    lam = (tq - t[before[-1]]) / (t[after[0]] - t[before[-1]])
    w[:, before.size - 1] -= 1.0 - lam                 # less the line through the two neighbours
    w[:, before.size] -= lam
    return float(np.abs(w @ v[nodes]).max()), float(np.linalg.norm(w, axis=1).max())


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of True in ``mask`` as (start, stop) index pairs."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))


def _np(v) -> np.ndarray:
    if isinstance(v, Tensor):
        return v.detach().cpu().numpy().astype(np.float64)
    return np.asarray(v, dtype=np.float64)


class Interpolant:
    """Batched, differentiable evaluation of all channels at times t of any shape.

    ``values(t)`` -> (*t.shape, c) spline values; ``mask(t)`` -> (*t.shape, c) in {0, 1}.
    """

    def __init__(self, data: Measurements, names: list[str], dtype=torch.float64, device=None):
        self.names = list(names)
        ts = data.t
        coef, valid = [], []
        for name in self.names:
            v = data.channels[name]
            ok = ~np.isnan(v)
            if ok.sum() >= 2:
                sp = CubicSpline(ts[ok], v[ok], bc_type="not-a-knot" if ok.sum() > 3 else "natural")
                c = sp(ts[:-1], 0), sp(ts[:-1], 1), sp(ts[:-1], 2) / 2.0, sp(ts[:-1], 3) / 6.0
            else:   # a single valid sample: constant
                c = (np.full(ts.size - 1, v[ok][0]),) + (np.zeros(ts.size - 1),) * 3
            coef.append(np.stack(c, -1))                        # (K−1, 4) Taylor coefficients per sample interval
            valid.append(ok[:-1] & ok[1:])
        self.t = torch.as_tensor(np.ascontiguousarray(ts), dtype=dtype, device=device)
        self.coef = torch.as_tensor(np.stack(coef, 1), dtype=dtype, device=device)     # (K−1, c, 4)
        self.valid = torch.as_tensor(np.stack(valid, 1), dtype=dtype, device=device)   # (K−1, c)

    def _locate(self, t: Tensor):
        k = (torch.searchsorted(self.t, t.detach().contiguous(), right=True) - 1).clamp(0, self.t.numel() - 2)
        return k, t - self.t[k]

    def values(self, t: Tensor) -> Tensor:
        k, d = self._locate(t)
        c = self.coef[k]                                   # (*t, c, 4)
        d = d.unsqueeze(-1)
        return c[..., 0] + d * (c[..., 1] + d * (c[..., 2] + d * c[..., 3]))

    def mask(self, t: Tensor) -> Tensor:
        return self.valid[self._locate(t)[0]]


# -- reading CSV files as people have them -------------------------------------------------
HUGE = 1e150            # |value| above this: its square (in J) overflows float64
OUTLIER = 1e6           # a value this many spreads from the median is taken for a typing/unit error
_SEPARATORS = (",", ";", "\t")
_MISSING = {"", "nan", "NaN", "NAN", "NA", "N/A", "n/a", "-"}
_UNIT = re.compile(r"^(?P<name>.*?)\s*(?:\[(?P<u1>[^\]]*)\]|\((?P<u2>[^)]*)\))\s*$")


def suspect_value(v: np.ndarray) -> tuple[int, str] | None:
    """The first value that would wreck an estimate, as (index, what is wrong): inf, a magnitude
    beyond :data:`HUGE` (its square overflows), or an outlier more than :data:`OUTLIER` times the
    spread of the others (1st to 99th percentile) away from their median (a typing or unit error)."""
    ok = ~np.isnan(v)
    if np.isinf(v).any():
        i = int(np.nonzero(np.isinf(v))[0][0])
        return i, "holds inf (leave the cell empty for a missing sample)"
    huge = ok & (np.abs(np.where(ok, v, 0.0)) > HUGE)
    if huge.any():
        i = int(np.nonzero(huge)[0][0])
        return i, f"holds {v[i]:.3g}; values beyond {HUGE:g} overflow the squared residuals"
    if ok.sum() < 10:
        return None
    lo, med, hi = np.percentile(v[ok], [1, 50, 99])
    spread = max(hi - lo, 1e-300)
    far = ok & (np.abs(np.where(ok, v, med) - med) > OUTLIER * spread)
    if far.any() and hi > lo:
        i = int(np.nonzero(far)[0][0])
        return i, (f"holds {v[i]:.3g}, more than {OUTLIER:.0e} times the spread of the other values "
                   f"({lo:.3g} to {hi:.3g}) from their median; a typing or unit error?")
    return None


def split_unit(header: str) -> tuple[str, str]:
    """``"t [s]"`` / ``"u (N)"`` -> ``("t", "s")`` / ``("u", "N")``; no unit -> ``(header, "")``."""
    h = header.strip().strip('"').strip()
    m = _UNIT.match(h)
    if m and m.group("name"):
        return m.group("name").strip(), (m.group("u1") if m.group("u1") is not None else m.group("u2")).strip()
    return h, ""


def _sniff_separator(lines: list[str]) -> str:
    """The separator among , ; TAB that splits the header and the first rows into the same,
    largest number of columns (``;`` wins over ``,`` when both do: decimal commas)."""
    best, best_cols = ",", 1
    for sep in (";", "\t", ","):
        counts = {len(next(csv.reader([ln], delimiter=sep))) for ln in lines}
        if len(counts) == 1 and (n := counts.pop()) > best_cols:
            best, best_cols = sep, n
    return best


def _number(cell: str, decimal_comma: bool) -> float:
    c = cell.strip()
    if c in _MISSING:
        return math.nan
    try:
        return float(c)
    except ValueError:
        if decimal_comma and c.count(",") == 1:
            return float(c.replace(",", "."))
        raise


def read_table(path: str | Path) -> Measurements:
    """A CSV file as a spreadsheet writes it: UTF-8 with or without a byte-order mark (else
    Latin-1), LF or CRLF, separated by ``,`` ``;`` or TAB (sniffed; with ``;`` or TAB a decimal
    comma is read too), units in the header (``t [s]``, ``u (N)``: kept in ``units``).  Empty
    cells, ``nan``, ``NA`` are missing samples.  A column with a non-numeric cell is set aside
    (``text``, with a ``notes`` line) and is an error only if a model needs it
    (:meth:`Measurements.require`); the time column ``t`` must be numeric.  Rows are counted as
    in a spreadsheet: the header is row 1."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a data file")
    if not path.is_file():
        raise ValueError(f"data file not found: {path}")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip()]
    if not lines:
        raise ValueError(f"{path}: empty file")
    sep = _sniff_separator([ln for _, ln in lines[:20]])
    rows = [(no, next(csv.reader([ln], delimiter=sep))) for no, ln in lines]
    names, units = [], {}
    for h in rows[0][1]:
        name, unit = split_unit(h)
        names.append(name)
        if unit:
            units[name] = unit
    while names and names[-1] == "" and all(len(r) < len(names) or not r[len(names) - 1].strip() for _, r in rows[1:]):
        names.pop()                         # a trailing separator on every line
    if "t" not in names:
        raise ValueError(f"{path}: the header row must have a time column 't' (found {names})")
    dup = sorted({n for n in names if names.count(n) > 1 and n})
    if dup:
        raise ValueError(f"{path}: column name(s) {dup} appear more than once in the header")
    body = rows[1:]
    if not body:
        raise ValueError(f"{path}: a header row but no data rows")
    for no, r in body:
        while len(r) > len(names) and not r[-1].strip():
            r.pop()
        if len(r) != len(names):
            raise ValueError(f"{path}: row {no} has {len(r)} cells, the header has {len(names)} "
                             f"(separator {sep!r})")
    comma = sep != ","
    cols: dict[str, np.ndarray] = {}
    text_cols: dict[str, str] = {}
    for j, name in enumerate(names):
        values = np.empty(len(body))
        for i, (no, r) in enumerate(body):
            try:
                values[i] = _number(r[j], comma)
            except ValueError:
                why = f"row {no} holds {r[j].strip()!r}, not a number"
                if name == "t":
                    raise ValueError(f"{path}: column 't' {why}") from None
                text_cols[name or f"column {j + 1}"] = why
                break
        else:
            if name and not np.isnan(values).all():
                cols[name] = values
            elif name or not np.isnan(values).all():
                text_cols[name or f"column {j + 1}"] = "it is empty"
    notes = [f"{path.name}: ignoring column(s) " + ", ".join(f"{k!r} ({v})" for k, v in text_cols.items())] \
        if text_cols else []
    rowno = [no for no, _ in body]
    for name, v in cols.items():
        bad = suspect_value(v)
        if bad is not None:
            raise ValueError(f"{path}: column {name!r} row {rowno[bad[0]]} {bad[1]}")
    t = cols.pop("t")
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise ValueError(f"{path}: column 't' has no time at row {rowno[bad[0]]}")
    back = np.nonzero(np.diff(t) <= 0)[0]
    if back.size:
        i = int(back[0])
        if t[i + 1] == t[i]:
            raise ValueError(f"{path}: duplicate time stamp t = {t[i]:g} at rows {rowno[i]} and {rowno[i + 1]}")
        raise ValueError(f"{path}: the times t must increase: row {rowno[i + 1]} has t = {t[i + 1]:g} after "
                         f"t = {t[i]:g} in row {rowno[i]}")
    return Measurements(t, cols, units=units, text=text_cols, notes=notes, source=str(path), rows=rowno)


def write_table(path: str | Path, table: Mapping[str, np.ndarray], columns: list[str] | tuple[str, ...]) -> Path:
    """Write ``columns`` of ``table`` as CSV with a one-line header; 17 significant digits, so that
    :func:`read_table` gets the same numbers back."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.column_stack([np.asarray(table[c], dtype=float) for c in columns]), delimiter=",",
               header=",".join(columns), comments="", fmt="%.17g")
    return path


def noise_level(data, channels: Sequence[str] | None = None, exact_zero: bool = False) -> dict[str, float]:
    """Noise standard deviation per channel from the data alone (no model): the spread of the 4th
    differences (robust: median absolute deviation; a smooth signal sampled densely has tiny 4th
    differences, white noise of std σ gives 4th differences of std √70 σ, Σ binom(4, k)² = 70).
    It reads the noise at the top of the band, above the model's dynamics: coloured noise is read
    low (80 % white + 20 % AR(1) with a correlation time of 4 samples: 0.91 σ), and for the
    diagnosis's noise floor that band is the one that matters.  At least 1e-6 of the channel's std — or, with
    ``exact_zero``, 0 for a channel whose 4th differences are mostly exactly zero (a piecewise
    linear input recorded exactly: its few kinks are not noise)."""
    data = Measurements.coerce(data)
    out: dict[str, float] = {}
    for ch in channels if channels is not None else list(data.channels):
        y = data.channels[ch]
        y = y[~np.isnan(y)]
        if y.size < 8:
            out[ch] = 0.0
            continue
        d = np.diff(y, n=4)
        mad = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(70.0)
        rms = float(np.sqrt(np.mean(d * d)) / math.sqrt(70.0))
        if exact_zero and mad == 0:
            out[ch] = 0.0
            continue
        s = mad if mad > 0 else rms
        out[ch] = max(s, 1e-6 * float(np.std(y)))
    return out
