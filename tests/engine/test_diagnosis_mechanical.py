"""The mechanical library for a declared model (shootlab.diagnosis.mechanical): the signs probed
from the rows and the terms that follow them, and the declaration's errors."""
from __future__ import annotations

import math

import pytest
import torch

from shootlab.diagnosis import library_for
from shootlab.diagnosis.mechanical import Mechanics, smooth_sign
from shared import axis


def test_declared_mechanics_probe_the_signs_and_the_terms_follow_them():
    """Orientation = sign of ∂motion/∂a, command coefficient = ∂motion/∂u; written either way round
    the Coulomb term opposes the motion (+o f σ(v)) and the gain error scales the applied force."""
    fwd, rev = axis(), axis(reverse=True)
    assert fwd.settings.mechanics == Mechanics(motion="motion", velocity="v", orientation=1.0, command="force",
                                                   command_coefficient=-2.0)
    assert rev.settings.mechanics.orientation == -1.0 and rev.settings.mechanics.command_coefficient == 2.0
    for model, o in ((fwd, 1.0), (rev, -1.0)):
        lib = library_for(model)
        assert lib.name == "mechanical[axis]"
        assert set(lib.names) == {"coulomb", "viscous", "stribeck", "input_gain", "input_offset", "input_saturation",
                                  "input_delay"}
        v = torch.linspace(-0.5, 0.5, 11, dtype=torch.float64)
        term = lib["coulomb"].term({"v": v, "coulomb_f": torch.full_like(v, 0.3)})
        vs = 1e-2                      # no record: the default half-width
        torch.testing.assert_close(term["motion"], o * 0.3 * smooth_sign(v, vs))


@pytest.mark.parametrize("spec, message", [
    (dict(motion="position"), "must name a model (not a measurement) row"),
    (dict(velocity="s"), "whose derivative is an input"),
    (dict(command="position"), "must be the channel of a measurement row that reads one input"),
    (dict(deflection="s"), "deflection and stiffness go together"),
    (dict(friction_width=0.0), "friction_width must be positive"),
    (dict(speed=1.0), "unknown key(s) ['speed']"),
])
def test_declared_mechanics_errors_name_the_problem(spec, message):
    with pytest.raises(ValueError, match=".*" + message.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]")):
        axis(**spec)


def test_a_stribeck_hump_narrower_than_the_signs_ramp_keeps_its_height():
    """The hump's own sign is ramped over v_h = v_st v_s/(v_st + v_s) < v_st, so at v = v_st the
    friction is f_c σ(v_st; v_s) + (f_s − f_c)/e, however narrow the hump against v_s (the level
    ramped as a whole would give (f_c + (f_s − f_c)/e) σ(v_st; v_s), a third of it at v_st = v_s/5);
    at f_s = f_c the law is Coulomb's, so that Stribeck nests Coulomb exactly."""
    lib = library_for(axis())
    vs = 1e-2
    stribeck, coulomb = lib["stribeck"], lib["coulomb"]
    for vst in (0.2 * vs, vs, 5.0 * vs):
        v = torch.tensor([vst, -vst], dtype=torch.float64)
        fc, fs = torch.full_like(v, 1.0), torch.full_like(v, 3.0)
        got = stribeck.term({"v": v, "stribeck_fc": fc, "stribeck_fs": fs, "stribeck_vst": torch.full_like(v, vst)})
        want = 1.0 * smooth_sign(v, vs) + 2.0 * math.exp(-1.0) * torch.sign(v)
        torch.testing.assert_close(got["motion"], want, rtol=1e-14, atol=0.0)
    assert float(got["motion"][0]) > 1.0 + 2.0 / 3.0       # above the Coulomb level where the hump is
    v = torch.linspace(-5 * vs, 5 * vs, 101, dtype=torch.float64)
    same = stribeck.term({"v": v, "stribeck_fc": torch.full_like(v, 0.7), "stribeck_fs": torch.full_like(v, 0.7),
                          "stribeck_vst": torch.full_like(v, 0.3 * vs)})
    torch.testing.assert_close(same["motion"], coulomb.term({"v": v, "coulomb_f": torch.full_like(v, 0.7)})["motion"],
                               rtol=0.0, atol=0.0)
