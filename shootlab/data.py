"""Measured time series: loading (tensors, arrays, CSV), checks and batched interpolation.

Each channel is interpolated in time by a cubic spline through its valid samples (C²,
so that high-order integrators keep their order between samples); missing samples (NaN)
are not interpolated over: the channel's *weight* ``mask(t)`` is zero on every sampling
interval that touches a missing sample, so they drop out of the cost instead of crashing it.
"""
from __future__ import annotations

import csv
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from torch import Tensor


@dataclass
class Measurements:
    """Sample times ``t`` (K,) and named channels (K,) each; NaN marks a missing sample."""

    t: np.ndarray
    channels: dict[str, np.ndarray]
    units: dict[str, str] = field(default_factory=dict)       # column -> unit from the header ("t [s]")
    text: dict[str, str] = field(default_factory=dict)        # ignored non-numeric column -> why
    notes: list[str] = field(default_factory=list)            # what the reader did (one line each)
    source: str = ""                                          # file name, for messages

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if self.t.size < 2:
            raise ValueError(f"{self._where()}measurements need at least two samples, got {self.t.size}")
        if not np.isfinite(self.t).all():
            raise ValueError("the time column t contains NaN or inf")
        if (np.diff(self.t) <= 0).any():
            i = int(np.nonzero(np.diff(self.t) <= 0)[0][0])
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
        raise ValueError(f"{path}: the times t must increase: row {rowno[i + 1]} has t = {t[i + 1]:g} after "
                         f"t = {t[i]:g} in row {rowno[i]}")
    return Measurements(t, cols, units=units, text=text_cols, notes=notes, source=str(path))


def write_table(path: str | Path, table: Mapping[str, np.ndarray], columns: list[str] | tuple[str, ...]) -> Path:
    """Write ``columns`` of ``table`` as CSV with a one-line header; 17 significant digits, so that
    :func:`read_table` gets the same numbers back."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.column_stack([np.asarray(table[c], dtype=float) for c in columns]), delimiter=",",
               header=",".join(columns), comments="", fmt="%.17g")
    return path
