"""The mechanics a declared model names (:func:`shootlab.model`, ``mechanics=``): its equation of motion, velocity, command and spring, with the signs read from its rows — what the diagnosis's mechanical library (:mod:`shootlab.diagnosis.mechanical`) builds its candidates from."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

from torch import Tensor



@dataclass
class Mechanics:
    """What a declared model names (``shootlab.model(mechanics=…)``), with the signs probed from
    its rows at compile time; kept in ``settings.mechanics``."""

    motion: str
    velocity: str
    orientation: float
    command: str | None = None
    command_coefficient: float = -1.0
    deflection: str | None = None
    stiffness: str | None = None
    friction_width: float | None = None


def declared_mechanics(spec: dict, states: Mapping[str, str], rows, channels: Mapping[str, str], F: Tensor) -> Mechanics:
    """The mechanics a declared model names (:func:`shootlab.model`, ``mechanics=``) checked, with
    the signs the library needs read from its rows' F (samples, r, nζ) at the default parameters:
    the orientation ∂motion/∂velocity' and the command's coefficient ∂motion/∂command.  ``rows``
    is the model's row set (``equations``, ``sizes``, ``x_at``, ``z_at``, ``row_at``,
    ``inputs``: :mod:`shootlab.estimation.declarative`)."""
    known = {"motion", "velocity", "command", "deflection", "stiffness", "friction_width"}
    bad = sorted(set(spec) - known)
    if bad:
        raise ValueError(f"mechanics: unknown key(s) {bad}; the keys are {', '.join(sorted(known))}")
    motion, velocity = spec.get("motion"), spec.get("velocity")
    if motion not in rows.equations or motion in channels or motion in rows.sizes:
        raise ValueError(f"mechanics: motion={motion!r} must name a model (not a measurement) row: "
                         f"{', '.join(r for r in rows.equations if r not in channels)}")
    if velocity not in states or states[velocity] not in rows.z_at or not isinstance(rows.x_at[velocity], int):
        raise ValueError(f"mechanics: velocity={velocity!r} must name a state whose derivative is an input "
                         f"(the acceleration), e.g. states={{'s': 'v', 'v': 'a'}}")
    i = rows.row_at[motion]

    def coefficient(j: int, what: str) -> float:
        c = F[:, i, j]
        if not (c > 0).all() and not (c < 0).all():
            raise ValueError(f"mechanics: the row {motion!r} must depend on {what} with one sign at the default "
                             f"parameters (found {c.min().item():.3g} … {c.max().item():.3g})")
        return float(c.mean())
    orientation = math.copysign(1.0, coefficient(rows.z_at[states[velocity]], f"{states[velocity]!r}"))
    out = Mechanics(motion=motion, velocity=velocity, orientation=orientation)
    command = spec.get("command")
    if command is not None:
        row = next((r for r, c in channels.items() if c == command), None)
        drivers = [] if row is None else [j for j in range(len(rows.inputs)) if F[:, rows.row_at[row], j].any()]
        if len(drivers) != 1:
            raise ValueError(f"mechanics: command={command!r} must be the channel of a measurement row that reads "
                             f"one input (as 'force': lambda x: x.u); channels are {', '.join(channels.values())}")
        j = drivers[0]
        out.command = command
        out.command_coefficient = coefficient(j, f"{rows.inputs[j]!r}") / float(F[:, rows.row_at[row], j].mean())
    d, k = spec.get("deflection"), spec.get("stiffness")
    if (d is None) != (k is None):
        raise ValueError("mechanics: deflection and stiffness go together (a spring's state and its parameter)")
    if d is not None:
        if d not in states or k not in rows.x_at or k in states:
            raise ValueError(f"mechanics: deflection={d!r} must be a state and stiffness={k!r} a parameter")
        out.deflection, out.stiffness = d, k
    if spec.get("friction_width") is not None:
        out.friction_width = float(spec["friction_width"])
        if not out.friction_width > 0:
            raise ValueError(f"mechanics: friction_width must be positive, got {spec['friction_width']!r}")
    return out
