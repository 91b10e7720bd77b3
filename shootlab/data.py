"""Measured time series: loading (tensors, arrays, CSV), checks and batched interpolation.

Each channel is interpolated in time by a cubic spline through its valid samples (C²,
so that high-order integrators keep their order between samples); missing samples (NaN)
are not interpolated over: the channel's *weight* ``mask(t)`` is zero on every sampling
interval that touches a missing sample, so they drop out of the cost instead of crashing it.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
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

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if self.t.size < 2:
            raise ValueError("measurements need at least two samples")
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
            if np.isinf(v).any():
                raise ValueError(f"channel {name!r} contains inf")
            if np.isnan(v).all():
                raise ValueError(f"channel {name!r} has no valid sample")
            chans[name] = v
        self.channels = chans

    @classmethod
    def from_csv(cls, path: str | Path) -> "Measurements":
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"data file not found: {path}")
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
        if not rows:
            raise ValueError(f"{path}: empty file")
        header = [h.strip() for h in rows[0]]
        if "t" not in header:
            raise ValueError(f"{path}: the header row must have a column 't' (found {header})")
        body = [r for r in rows[1:] if r and any(c.strip() for c in r)]
        try:
            arr = np.array([[float(c) if c.strip() not in ("", "nan", "NaN") else np.nan for c in r]
                            for r in body], dtype=np.float64)
        except ValueError as exc:
            raise ValueError(f"{path}: non-numeric entry ({exc})") from None
        if arr.ndim != 2 or arr.shape[1] != len(header):
            raise ValueError(f"{path}: every row must have {len(header)} columns")
        cols = {h: arr[:, i] for i, h in enumerate(header)}
        return cls(cols.pop("t"), cols)

    @classmethod
    def coerce(cls, data) -> "Measurements":
        """Measurements, a CSV path, or a mapping with key 't' and channel arrays/tensors."""
        if isinstance(data, Measurements):
            return data
        if isinstance(data, (str, Path)):
            return cls.from_csv(data)
        if isinstance(data, Mapping):
            if "t" not in data:
                raise ValueError("measurement mapping needs a key 't'")
            cols = {k: _np(v) for k, v in data.items() if k != "t"}
            return cls(_np(data["t"]), cols)
        raise ValueError(f"cannot read measurements from {type(data).__name__}")

    def to_csv(self, path: str | Path) -> None:
        names = list(self.channels)
        arr = np.column_stack([self.t] + [self.channels[k] for k in names])
        np.savetxt(path, arr, delimiter=",", header=",".join(["t"] + names), comments="", fmt="%.12g")

    def require(self, names, start: float, end: float) -> None:
        missing = [n for n in names if n not in self.channels]
        if missing:
            raise ValueError(f"the data lack channel(s) {missing}; it has {sorted(self.channels)}")
        if self.t[0] > start + 1e-12 * max(1.0, abs(start)) or self.t[-1] < end - 1e-12 * max(1.0, abs(end)):
            raise ValueError(f"the data cover [{self.t[0]}, {self.t[-1]}], shorter than the interval [{start}, {end}]")


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
