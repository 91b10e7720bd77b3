"""The declarative model (shootlab/estimation/declarative.py): compiled values, blocks, errors,
settings, data-scaled default weights, and an estimate."""
import copy
import dataclasses
import math

import numpy as np
import pytest
import torch

from shootlab.estimation.data import Measurements
from shootlab.estimation.declarative import model
from shootlab.estimation.settings import EstimationSettings
from shootlab.estimation import IdentificationModel, estimate
from shared import DRIVE, drive_record


def _oscillator(**changes):
    """A small model with a non-linear f and an F that depends on the states:
    m a + b v|v| + k sin s = u,  pos = s,  force = u,  with ζ = [u, a] (force first)."""
    decl = dict(name="osc", states={"s": "v", "v": "a"}, inputs=["u", "a"],
                parameters={"m": 2.0, "b": 0.5, "k": 3.0},
                equations={"motion": lambda x: x.m * (1 + x.s ** 2) * x.a + x.b * x.v * x.v.abs()
                           + x.k * torch.sin(x.s) - x.u,
                           "pos": lambda x: x.s, "force": lambda x: x["u"]},
                channels={"pos": "s_m", "force": "u_m"})
    decl.update(changes)
    return model(**decl)


def _hand_f(x, t):
    s, v, m, b, k = x.unbind(-1)
    return torch.stack([b * v * v.abs() + k * torch.sin(s), s, torch.zeros_like(s)], -1)


def _hand_F(x, t):
    s, v, m, b, k = x.unbind(-1)
    one, zero = torch.ones_like(s), torch.zeros_like(s)
    return torch.stack([torch.stack([-one, m * (1 + s ** 2)], -1), torch.stack([zero, zero], -1),
                        torch.stack([one, zero], -1)], -2)


def test_compiled_A_B_f_F_equal_the_hand_written_ones():
    md = _oscillator()
    assert isinstance(md, IdentificationModel)
    assert md.names == ["s", "v", "m", "b", "k"] and md.inputs == ["u", "a"]
    assert md.equations == ["motion", "pos", "force"] and md.channels == {"pos": "s_m", "force": "u_m"}
    A = torch.zeros(5, 5, dtype=torch.float64)
    A[0, 1] = 1.0                                    # s' = v
    B = torch.zeros(5, 2, dtype=torch.float64)
    B[1, 1] = 1.0                                    # v' = a
    assert torch.equal(md.A, A) and torch.equal(md.B, B)
    x = torch.randn(3, 4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    t = torch.rand(3, 4, dtype=torch.float64)
    f, F = md.f(x, t), md.F(x, t)
    assert f.dtype == F.dtype == torch.float64 and f.shape == (3, 4, 3) and F.shape == (3, 4, 3, 2)
    torch.testing.assert_close(f, _hand_f(x, t), rtol=0, atol=0)       # the same operations: bit-equal
    torch.testing.assert_close(F, _hand_F(x, t), rtol=0, atol=0)
    # a single sample (x (nx,), t scalar) as the free-run simulation calls them
    torch.testing.assert_close(md.F(x[0, 0], t[0, 0]), _hand_F(x[0, 0], t[0, 0]), rtol=0, atol=0)
    # defaults: the prior, W 1e10 on states and 1 on parameters, V 1, the force channel given
    assert md.prior == {"m": 2.0, "b": 0.5, "k": 3.0}
    assert md.W == [1e10, 1e10, 1.0, 1.0, 1.0] and md.V == [1.0, 1.0, 1.0] and md.given == ["u_m"]


def _chain(N: int = 6, **changes):
    """N masses in a chain between walls, one block each: m a_i + k (2 s_i − s_{i−1} − s_{i+1}) = u_i,
    the first mass's position measured, every force given."""
    def spring(s):
        pad = s.new_zeros(*s.shape[:-1], 1)
        return 2 * s - torch.cat([pad, s[..., :-1]], -1) - torch.cat([s[..., 1:], pad], -1)
    decl = dict(name="chain", states={"s": "v", "v": "a"}, inputs=["a", "u"], parameters={"m": 1.5, "k": 2.0},
                blocks={"s": N, "v": N, "a": N, "u": N, "motion": N, "force": N},
                equations={"motion": lambda x: x.m[..., None] * x.a + x.k[..., None] * spring(x.s) - x.u, "force": lambda x: x.u,
                           "pos": lambda x: x.s[..., 0]},
                channels=["pos"])
    decl.update(changes)
    return model(**decl)


def test_blocks_compile_to_components_and_probe_in_groups():
    N = 6
    md = _chain(N)
    assert md.states == [f"s{i}" for i in range(1, N + 1)] + [f"v{i}" for i in range(1, N + 1)]
    assert md.inputs == [f"a{i}" for i in range(1, N + 1)] + [f"u{i}" for i in range(1, N + 1)]
    assert md.equations == [f"motion{i}" for i in range(1, N + 1)] + [f"force{i}" for i in range(1, N + 1)] + ["pos"]
    eye = torch.eye(N, dtype=torch.float64)
    assert torch.equal(md.A[:N, N:2 * N], eye) and torch.equal(md.B[N:2 * N, :N], eye)     # s' = v, v' = a
    assert not md.A[N:].any() and not md.B[:N].any() and not md.B[:, N:].any()
    x = torch.randn(7, 2 * N + 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    t = torch.zeros(7, dtype=torch.float64)
    F = md.F(x, t)
    rows = md.F.__self__
    assert rows.colors is not None and int(rows.colors.max()) + 1 == 2        # a_i and u_i share row motion_i
    m = x[:, -2]
    hand = torch.zeros(7, 2 * N + 1, 2 * N, dtype=torch.float64)
    hand[:, :N, :N] = m[:, None, None] * eye
    hand[:, :N, N:] = -eye
    hand[:, N:2 * N, N:] = eye
    assert torch.equal(F, hand)
    full = copy.copy(rows)
    full.colors = None                                        # one probe per input
    assert torch.equal(full.F(x, t), F)
    s, k = x[:, :N], x[:, -1]
    want = k[:, None] * (2 * s - torch.nn.functional.pad(s[:, :-1], (1, 0)) - torch.nn.functional.pad(s[:, 1:], (0, 1)))
    torch.testing.assert_close(md.f(x, t)[:, :N], want, rtol=0, atol=1e-15)
    assert torch.equal(md.f(x, t)[:, -1], s[:, 0])


@pytest.mark.parametrize("changes, words", [
    (dict(blocks={"s": 3, "v": 4, "a": 4, "u": 4, "motion": 4, "force": 4}), ["state 's' and its derivative 'v'"]),
    (dict(blocks={"s": 3, "v": 3, "a": 3, "u": 3, "motion": 3, "force": 3, "pos": 3}), ["block 'pos' is a measurement row"]),
    (dict(blocks={"s": 3, "v": 3, "a": 3, "u": 3, "motion": 3, "force": 3, "m": 2}), ["block 'm' is not a state"]),
    (dict(blocks={"s": 3, "v": 3, "a": 3, "u": 3, "motion": 2, "force": 3}), ["row 'motion' returns shape", "2 values per sample"]),
])
def test_block_errors_name_the_problem(changes, words):
    with pytest.raises(ValueError) as err:
        _chain(**changes)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_a_written_out_F_is_checked_against_the_rows():
    assert _oscillator(F=_hand_F).F is _hand_F
    with pytest.raises(ValueError, match=r"F differs from the rows' derivative in the inputs: ∂motion/∂a"):
        _oscillator(F=lambda x, t: _hand_F(x, t) * torch.tensor([[1.0, 1.001], [1.0, 1.0], [1.0, 1.0]], dtype=x.dtype))
    with pytest.raises(ValueError, match="F returns shape"):
        _oscillator(F=lambda x, t: _hand_F(x, t)[..., :1])


def test_one_affine_check_for_model_rows_and_effect_terms():
    """``not_affine`` (the check of a declared model's rows and of an effect's terms): rows
    affine in ζ with a large ζ-free part (1e12 + 3ζ₁, rounded to ε of it) pass; a product
    ζ₁ζ₂ and |ζ₁| (positively homogeneous: right on ζ = 2 z, wrong at a negative ζ₁) are named;
    a row that is NaN at the sample proves nothing.  The one namespace of rows and terms reads
    ``x.name`` and ``x["name"]`` alike, ``x.input`` an input by name, and an unknown name is one
    error for both (an AttributeError and a KeyError)."""
    from shootlab.estimation.rows import UnknownName, Variables, not_affine

    gen = torch.Generator().manual_seed(3)
    z = torch.randn(6, 2, generator=gen, dtype=torch.float64)
    z = torch.stack([z, -z.abs()])                    # two samples, one with ζ₁ < 0 everywhere

    def value(zeta):
        a, b = zeta.unbind(-1)
        return torch.stack([1e12 + 3 * a, a * b, a.abs(), torch.full_like(a, math.nan)], -1)
    f = value(torch.zeros(6, 2, dtype=torch.float64))
    F = torch.stack([value(torch.eye(2, dtype=torch.float64)[j].expand(6, 2)) - f for j in range(2)], -1)
    assert not_affine(value, f, F, z) == [1, 2]
    v = Variables({"s": torch.ones(3), "t": torch.zeros(3)}, inputs={"s": 2 * torch.ones(3), "u": torch.ones(3)})
    assert v.s is v["s"] and float(v.input("s")[0]) == 2.0 and float(v.u[0]) == 1.0 and "u" in v
    for read in (lambda: v.mass, lambda: v["mass"]):
        with pytest.raises(UnknownName, match="no variable named 'mass'; known names: s, u, t"):
            read()
    assert isinstance(UnknownName("m", []), KeyError) and isinstance(UnknownName("m", []), AttributeError)


def test_compiled_rows_compose_with_torch_func():
    """The engine differentiates f and F by jvp (under vmap) and vjp: the same derivatives as the
    hand-written functions."""
    md = _oscillator()
    x = torch.randn(6, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    dirs = torch.eye(5, dtype=torch.float64)
    for ours, hand in ((md.f, _hand_f), (md.F, _hand_F)):
        def along(fn):
            return torch.func.vmap(lambda d: torch.func.jvp(lambda xx: fn(xx, t), (x,), (d.expand_as(x),))[1])(dirs)
        torch.testing.assert_close(along(ours), along(hand), rtol=1e-14, atol=1e-14)
        cot = torch.randn_like(hand(x, t))
        g1 = torch.func.vjp(lambda xx: ours(xx, t), x)[1](cot)[0]
        g2 = torch.func.vjp(lambda xx: hand(xx, t), x)[1](cot)[0]
        torch.testing.assert_close(g1, g2, rtol=1e-14, atol=1e-14)


def test_weights_per_name_settings_and_list_channels():
    prefit = lambda data, params, t: params                                # noqa: E731
    md = _oscillator(W={"v": 1e8, "k": 5.0}, V={"pos": 1e4}, W_a={"s": 1.0}, q_a={"s": 0.5},
                     channels=["pos", "force"], given=[],
                     settings=EstimationSettings(points=51, solver=dict(integrator="euler", steps=2),
                                                 prefit=prefit, weight_continuation=[1.0, 100.0],
                                                 extra={"length": 2.0}))
    assert md.W == [1e10, 1e8, 1.0, 1.0, 5.0] and md.V == [1.0, 1e4, 1.0]
    assert md.W_a == [1.0, 0.0, 0.0, 0.0, 0.0] and md.q_a.tolist() == [0.5, 0, 0, 0, 0]
    assert md.channels == {"pos": "pos", "force": "force"} and md.given == []
    assert md.settings == EstimationSettings(
        points=51, solver={"integrator": "euler", "steps": 2}, prefit=prefit, weight_continuation=(1.0, 100.0),
        # the entries left to the defaults, scaled by the data when estimated
        weights_from_data={"W": [1e10, None, 1.0, 1.0, None], "V": [1.0, None, 1.0]}, extra={"length": 2.0})
    assert md.settings.weight_continuation == (1.0, 100.0) and md.settings.extra["length"] == 2.0
    assert (EstimationSettings().points, EstimationSettings().solver) == (101, {"integrator": "rk4", "steps": 10})
    assert EstimationSettings(span=10).span == 10.0 and EstimationSettings(points=51.0).points == 51
    assert md.settings.replace(points=201).points == 201 and md.settings.points == 51      # a changed copy
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="span must be a positive record length"):
            EstimationSettings(span=bad)


def test_default_initial_states_from_the_measured_state_and_its_derivative():
    md = _oscillator(settings=EstimationSettings(smoothing=21))
    ts = np.linspace(0, 2, 201)
    data = Measurements(ts, {"s_m": np.sin(ts), "u_m": np.cos(ts)})
    t = torch.linspace(0.1, 1.9, 7, dtype=torch.float64)
    x0 = md.initial_states(data, t)
    np.testing.assert_allclose(x0[:, 0].numpy(), np.sin(t.numpy()), atol=1e-9)       # s from its channel
    np.testing.assert_allclose(x0[:, 1].numpy(), np.cos(t.numpy()), atol=1e-6)       # v = s' by Savitzky–Golay


@pytest.mark.parametrize("changes, words", [
    (dict(equations={"motion": lambda x: x.mass * x.a - x.u, "pos": lambda x: x.s, "force": lambda x: x.u}),
     ["row 'motion'", "unknown name 'mass'", "known names: s, v, m, b, k, u, a, t"]),
    (dict(states={"s": "v", "v": "m"}), ["state 'v'", "derivative 'm'", "neither a state", "nor an input"]),
    (dict(states={"s": "v", "v": "acc"}), ["state 'v'", "derivative 'acc'"]),
    (dict(equations={"motion": lambda x: x.m * x.a * x.a - x.u, "pos": lambda x: x.s, "force": lambda x: x.u}),
     ["row 'motion' is not affine in the inputs"]),
    (dict(channels={"pos": "s_m", "speed": "v_m"}), ["'v_m'", "row 'speed'", "not an equation row"]),
    (dict(inputs=["u", "a", "jerk"]), ["input(s) ['jerk'] enter no equation row"]),
    (dict(parameters={"m": 1.0, "s": 2.0}), ["'s' is declared twice"]),
    (dict(parameters={"m": 1.0, "t": 2.0}), ["the name t is the time"]),
    (dict(parameters={"m": float("nan")}), ["parameter 'm'", "finite number"]),
    (dict(W={"q": 1.0}), ["W names ['q']"]),
    (dict(equations={"motion": lambda x: torch.stack([x.m * x.a - x.u, x.s], -1), "pos": lambda x: x.s,
                     "force": lambda x: x.u}), ["row 'motion' returns shape", "one value per sample"]),
    (dict(equations={"motion": lambda x: x.m * x.a - x.u + x.s.numpy().sum(), "pos": lambda x: x.s,
                     "force": lambda x: x.u}), ["row 'motion' fails", "out-of-place"]),
    (dict(equations={"motion": lambda x: x.m * x.a - x.u + float(x.s.sum()), "pos": lambda x: x.s,
                     "force": lambda x: x.u}), ["row 'motion' loses its derivative"]),
    (dict(equations={}), ["at least one equation"]),
    (dict(inputs=[]), ["at least one input"]),
    (dict(settings=dict(points=5)), ["settings must be an EstimationSettings"]),
    (dict(bounds={"mass": (0, 1)}), ["bounds for 'mass'"]),
])
def test_declaration_errors_are_one_line_value_errors(changes, words):
    with pytest.raises(ValueError) as err:
        _oscillator(**changes)
    msg = str(err.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_settings_errors():
    with pytest.raises(ValueError, match=r"solver options \['stepz'\] are not options of shootlab.solve"):
        EstimationSettings(solver=dict(stepz=3))
    with pytest.raises(ValueError, match="smoothing must be an odd window"):
        EstimationSettings(smoothing=10)
    with pytest.raises(ValueError, match="points must be an integer of at least 2, got 1.5"):
        EstimationSettings(points=1.5)
    with pytest.raises(ValueError, match="refine must be a callable or None, got str"):
        EstimationSettings().replace(refine="finer")
    with pytest.raises(dataclasses.FrozenInstanceError):
        EstimationSettings().points = 3
    with pytest.raises(ValueError, match="settings must be a shootlab.EstimationSettings, got dict"):
        dataclasses.replace(_oscillator(), settings={"points": 51})


# -- an estimate of the one-axis drive of docs/your_own_model.md -----------------------------------------------------


def _drive_in(unit: float, **weights):
    """The drive with positions in metres / ``unit`` (unit 1e-3: millimetres): m and b in N per
    (that unit / s²) and (that unit / s), initial values 1 N s²/m and 1 N s/m in that unit."""
    return model(name="drive", states={"s": "v", "v": "a"}, inputs=["a", "u"],
                 parameters={"m": unit, "b": unit, "c": 0.0},
                 equations={"motion": lambda x: x.m * x.a + x.b * x.v + x.c - x.u,
                            "position": lambda x: x.s, "force": lambda x: x.u},
                 channels=["position", "force"], bounds={"m": (0.0, math.inf)}, **weights)


def test_default_weights_from_the_data_make_the_estimate_unit_invariant():
    """Issue 12 item 3: the same record and model in metres and in millimetres give the same m, b, c
    (converted) with the default weights, which are scaled by the data (shootlab.estimation.weights).  The
    report's literal weights (W 1e10 / 1, V 1) fit the metre version only: in millimetres the
    position residual weighs 10⁶ times more and the Newton iteration fails."""
    rec = drive_record(0.01)
    in_mm = dict(rec, position=1e3 * rec["position"])
    si, mm = estimate(_drive_in(1.0), rec), estimate(_drive_in(1e-3), in_mm)
    assert si.success and mm.success, (si.message, mm.message)
    for p, v in DRIVE.items():
        assert si.parameters[p] == pytest.approx(v, rel=1e-2), si.parameters
        to_si = 1e3 if p in ("m", "b") else 1.0
        assert mm.parameters[p] * to_si == pytest.approx(si.parameters[p], rel=1e-9), (p, mm.parameters)
    literal = dict(W=[1e10, 1e10, 1.0, 1.0, 1.0], V=[1.0, 1.0, 1.0])
    assert estimate(_drive_in(1.0, **literal), rec).success
    assert not estimate(_drive_in(1e-3, **literal), in_mm, fallback=False).success     # (armijo, trust_region: too)


def test_data_scales_of_the_drive():
    """The scales of shootlab.estimation.weights on the drive: the position's and the force's spread, the
    velocity's from the differentiated position, m and b by their initial values, the offset c
    (initial value 0) by the size of the motion row it enters with coefficient 1."""
    from shootlab.estimation.weights import scales

    rec = Measurements.coerce(drive_record(0.0))
    S, R = scales(_drive_in(1.0), rec)
    pos, force = rec.channels["position"], rec.channels["force"]
    assert float(S[0]) == pytest.approx(np.std(pos), rel=1e-2)
    assert float(S[1]) == pytest.approx(np.std(np.gradient(pos, rec.t)), rel=2e-2)
    # c's scale is the motion row's size without c; with c's term (as big) the row grows by √2
    assert S[2:4].tolist() == [1.0, 1.0] and float(S[4]) == pytest.approx(float(R[0]) / math.sqrt(2))
    assert float(R[1]) == pytest.approx(float(S[0])) and float(R[2]) == pytest.approx(np.std(force), rel=1e-9)


def test_an_extended_model_keeps_its_data_scaled_weights():
    """composition.extend on a model whose default weights are still to be scaled: the new
    parameter's weight is scaled as the others' (its scale: the size of the row it enters)."""
    from shootlab.diagnosis.composition import extend
    from shootlab.diagnosis.effects import Effect
    from shootlab.estimation.weights import from_data

    drive = _drive_in(1.0)
    offset = Effect("offset", ["motion"], {"offset": 0.0}, lambda v: {"motion": v["offset"]})
    ext = extend(drive, [offset])
    assert ext.settings.weights_from_data["W"] == [1e10, 1e10, 1.0, 1.0, 1.0, 1.0]
    rec = Measurements.coerce(drive_record(0.0))
    W = from_data(ext, rec).W
    assert float(W[5]) == pytest.approx(float(W[4]), rel=1e-9)      # offset and c: the same scale
