"""Virtual rig: a high-fidelity simulator of the flexible rotation manipulator.

It produces the "measured" data a real set-up would (report ch. 4, DESIGN §3), plus the
true noise-free states for tests, and a data generator for the mass–spring–damper example
of report §3.4.

Model (everything divided by the motor constant ``c``; parameters are the ``/c`` values)
----------------------------------------------------------------------------------------
States ``s1`` (end-effector angle), ``s2`` (rotor angle), ``v1 = s1'``, ``v2 = s2'``::

    m1 v1' =  k (s2 - s1) + b (v2 - v1) - f1(v1)
    m2 v2' =  u_app - k (s2 - s1) - b (v2 - v1) - f2(v2)

Sign conventions: all angles positive in the same rotational direction; a positive motor
torque accelerates the rotor positively; the torsion spring/damper act on the end-effector
with ``+k (s2 - s1) + b (v2 - v1)`` and react on the rotor with the opposite sign; friction
``f_i(v)`` has the sign of ``v`` and is subtracted (it opposes the motion).
``u_app`` is the applied torque/c, which differs from the *commanded* (and "measured")
motor signal ``u`` when the gain/delay/zero-order-hold effects are on::

    u_app(t) = gain * u_cmd(t - delay)          (u_cmd = 0 for t < 0)

The right-hand side is written once, :class:`TwoInertia`, with hooks for the friction laws,
the spring law and the input transformation; :func:`simulate_rig` sets them from
:class:`RigSettings` (smooth Coulomb with varying levels, ``gain * u_cmd(t - delay)``) and
:mod:`manipulators.rig_effects` from the diagnosis library's named effects. Each simulator
keeps its own record post-processing (here: ZOH, quantisation, noise).

Cross-check with the report (OCR of Eq. 4.1e/4.4b, partly illegible): the end-effector row
of ``f(x,t)`` reads ``k*(s2 - s1) + b*(v2 - v1)`` and the rotor row
``-k*(s2 - s1) - b*(v2 - v1)``, with the input entering only the rotor row — the same as
above. The sign of the friction term in Eq. 4.4b cannot be read reliably; we use the
physical convention (friction opposes velocity).

Default parameters are the report's extended-model estimates: m1/c = 5.40, m2/c = 0.47,
k/c = 1000, b/c = 2.3, f1/c = 1.26, f2/c = 39.9. The flexible-mode frequency
``sqrt(k (1/m1 + 1/m2)) / (2 pi)`` is 7.65 Hz with these values (8.29 Hz with the report's
prior values 4.7/0.39/978; the report quotes "approximately 8.5 Hz" from an impulse
response). See :func:`eigenfrequency_hz`.

Realism effects (each switchable in :class:`RigSettings`)
---------------------------------------------------------
* ``friction``: smooth Coulomb friction on both bodies with a small transition half-width
  (``v_s1 = v_s2 = 0.02 rad/s`` by default, i.e. nearly a sign function);
* ``friction_variation``: the Coulomb levels vary slowly in time,
  ``f_i(t) = f_i (1 + a sin(2 pi nu_i t + phi_i))``, ``a = 3 %``, ``nu_i`` in 0.3–1.5 Hz
  and ``phi_i`` drawn from the seed;
* ``gain_error``: applied torque = ``gain * command`` (``gain = 0.95``);
* ``delay``: the command reaches the motor ``delay = 2 ms`` late (exact for callables,
  linear interpolation for sampled arrays);
* ``zoh``: the command is output by a DAC with zero-order hold at the sample rate
  (the applied torque is piecewise constant; integrated segment by segment);
* ``quantization``: encoder readings are multiples of ``2 pi / encoder_counts``
  (8000 counts/rev, a 2000-line encoder with quadrature: 7.85e-4 rad);
* ``noise``: Gaussian noise ``noise_std = 2e-4 rad`` added to the angles before
  quantisation (and optionally ``u_noise_std`` on the recorded command, 0 by default);
* sampling at ``sample_rate = 1000 Hz``; ``duration = 1 s`` gives 1001 samples including
  both ends.

Presets: ``RigSettings()`` has every effect on; ``RigSettings.ideal()`` is the linear
two-mass system (no friction, every effect off); ``RigSettings.friction_only()`` keeps only
constant smooth Coulomb friction, with the report's model transition widths v_s1 = 0.1,
v_s2 = 1.0 rad/s (so the extended model has exactly the rig's structure), and no gain
error, delay, ZOH, quantisation or noise — the data on which the extended model must
recover the rig's parameters.

All randomness comes from ``numpy.random.SeedSequence(seed)`` with separate child streams for
the friction variation and the noise, so switching one effect does not change the other.

Inputs
------
* :func:`sine_sweep`: linear chirp 4 → 14 Hz over 1 s (bracketing both the model's 7.65 Hz
  and the report's 8.5 Hz), amplitude 150 (torque/c units). ``(f0 + f1) T / 2 = 9`` whole
  cycles, so the signal is 0 at both ends. With friction on, this gives angles of about
  -0.15 … 0.8 rad, rotor speeds of ~9 rad/s rms and end-effector speeds of ~1 rad/s rms,
  well above the friction transition most of the time (the report's figure 4.3 axes show a
  command scale of ~100 and angles up to ~1 rad). With the report's model widths
  (v_s2 = 1, v_s1 = 0.1 rad/s) the rotor is inside the transition ~11 % of the time and
  the end-effector ~9 % (zero crossings of an oscillation cannot be avoided).
* ``"pd"``: closed-loop validation signal — a discrete PD controller (1 kHz, on the
  measured encoder angles with filtered-difference velocities) makes the end-effector follow
  smoothed steps (0.3, -0.5, +0.35 rad starting at 0.05, 0.35, 0.65 s, 0.12 s rise); the
  torque it commands (a few hundred units, uncorrelated with the sweep) is the recorded
  ``u``. See :class:`PDController` and :func:`pd_validation_input`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from .friction import smooth_coulomb

__all__ = [
    "RigSettings",
    "RigData",
    "PDController",
    "TwoInertia",
    "eigenfrequency_hz",
    "linear_system_matrices",
    "sine_sweep",
    "smoothed_steps",
    "pd_validation_input",
    "simulate_rig",
    "msd_input",
    "msd_data",
    "msd_noisy_data",
    "save_csv",
    "load_csv",
]

TWO_PI = 2.0 * math.pi


# =============================================================================== settings
@dataclass(frozen=True)
class RigSettings:
    """Parameters, effect switches and numerics of the virtual rig (all values per unit ``c``)."""

    # physical parameters (report's extended-model estimates)
    m1: float = 5.40
    m2: float = 0.47
    k: float = 1000.0
    b: float = 2.3
    # friction
    friction: bool = True
    f1: float = 1.26
    f2: float = 39.9
    v_s1: float = 0.02
    v_s2: float = 0.02
    friction_variation: bool = True
    friction_variation_amplitude: float = 0.03
    friction_variation_freq: tuple[float, float] = (0.3, 1.5)
    # actuator
    gain_error: bool = True
    gain: float = 0.95
    delay_enabled: bool = True
    delay: float = 0.002
    zoh: bool = True
    # sensors
    quantization: bool = True
    encoder_counts: int = 8000
    noise: bool = True
    noise_std: float = 2e-4
    u_noise_std: float = 0.0
    sample_rate: float = 1000.0
    seed: int = 0
    # numerics
    initial_state: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    method: str = "DOP853"
    rtol: float = 1e-10
    atol: float = 1e-12

    # ---- presets
    @classmethod
    def ideal(cls, **overrides) -> "RigSettings":
        """Linear two-mass system: no friction, no actuator or sensor effects."""
        kw = dict(
            friction=False,
            friction_variation=False,
            gain_error=False,
            delay_enabled=False,
            zoh=False,
            quantization=False,
            noise=False,
        )
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def friction_only(cls, v_s1: float = 0.1, v_s2: float = 1.0, **overrides) -> "RigSettings":
        """Constant smooth Coulomb friction and nothing else (no gain error, no delay, no ZOH,
        no quantisation, no noise).

        The transition half-widths default to the report's extended-model values
        (v_s1 = 0.1, v_s2 = 1.0 rad/s), so that the extended model has *exactly* the rig's
        structure and must recover its parameters.
        """
        return cls.ideal(**{"friction": True, "v_s1": v_s1, "v_s2": v_s2, **overrides})

    def replace(self, **changes) -> "RigSettings":
        return dataclasses.replace(self, **changes)

    # ---- derived quantities
    @property
    def effective_gain(self) -> float:
        return float(self.gain) if self.gain_error else 1.0

    @property
    def effective_delay(self) -> float:
        return float(self.delay) if self.delay_enabled else 0.0

    @property
    def quantization_step(self) -> float:
        return TWO_PI / self.encoder_counts

    @property
    def eigenfrequency_hz(self) -> float:
        return eigenfrequency_hz(self.m1, self.m2, self.k)

    @property
    def params(self) -> dict[str, float]:
        """The identifiable parameters ``m1, m2, k, b, f1, f2`` (per unit c)."""
        return dict(m1=self.m1, m2=self.m2, k=self.k, b=self.b, f1=self.f1, f2=self.f2)


def eigenfrequency_hz(m1: float = 5.40, m2: float = 0.47, k: float = 1000.0) -> float:
    """Undamped flexible-mode frequency ``sqrt(k (1/m1 + 1/m2)) / (2 pi)`` in Hz."""
    return math.sqrt(k * (1.0 / m1 + 1.0 / m2)) / TWO_PI


def linear_system_matrices(m1=5.40, m2=0.47, k=1000.0, b=2.3):
    """``x' = A x + B u`` for ``x = [s1, s2, v1, v2]`` without friction."""
    A = np.array(
        [
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [-k / m1, k / m1, -b / m1, b / m1],
            [k / m2, -k / m2, b / m2, -b / m2],
        ]
    )
    B = np.array([[0.0], [0.0], [0.0], [1.0 / m2]])
    return A, B


# =============================================================================== inputs
def sine_sweep(t, amplitude: float = 150.0, f_start: float = 4.0, f_end: float = 14.0,
               duration: float = 1.0):
    """Linear sine sweep (chirp) ``A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T)))`` on
    ``[0, T]``, zero outside. Defaults: 4 → 14 Hz, amplitude 150, T = 1 s."""
    if type(t) in (float, int, np.float64):         # a simulator's call: math's scalar sine
        if not 0.0 <= t <= duration:
            return 0.0
        return float(amplitude * math.sin(TWO_PI * (f_start * t + 0.5 * (f_end - f_start) * t * t / duration)))
    t = np.asarray(t, dtype=float)
    phase = TWO_PI * (f_start * t + 0.5 * (f_end - f_start) * t * t / duration)
    out = np.where((t >= 0.0) & (t <= duration), amplitude * np.sin(phase), 0.0)
    return float(out) if out.ndim == 0 else out


def smoothed_steps(t, times: Sequence[float] = (0.05, 0.35, 0.65),
                   heights: Sequence[float] = (0.3, -0.5, 0.35), rise: float = 0.12,
                   derivative: bool = False):
    """Reference of smoothed steps: step ``j`` of size ``heights[j]`` starts at ``times[j]``
    and rises over ``rise`` seconds with the sinusoidal-acceleration profile
    ``x - sin(2 pi x) / (2 pi)`` (zero velocity at both ends). With ``derivative=True`` the
    time derivative is returned."""
    t = np.asarray(t, dtype=float)
    out = np.zeros_like(t)
    for t0, h in zip(times, heights):
        x = np.clip((t - t0) / rise, 0.0, 1.0)
        if derivative:
            out = out + h * (1.0 - np.cos(TWO_PI * x)) / rise * ((t > t0) & (t < t0 + rise))
        else:
            out = out + h * (x - np.sin(TWO_PI * x) / TWO_PI)
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class PDController:
    """Discrete PD position controller on both encoders, running at the rig's sample rate::

        u_k = kp1 (r_k - s1_k) + kd1 (r'_k - w1_k) + kp2 (r_k - s2_k) + kd2 (r'_k - w2_k)
        w_k = a w_{k-1} + (1 - a) (s_k - s_{k-1}) fs,   a = exp(-2 pi f_v / fs)

    ``s1_k, s2_k`` are the *measured* (quantised, noisy) encoder readings and ``w1, w2``
    filtered-difference velocities (cut-off ``velocity_cutoff_hz``). ``u_k`` is held until the
    next sample and reaches the motor through the rig's gain/delay. Both bodies follow the
    same reference (at rest ``s1 = s2`` since there is no external load).

    Default gains: position loop mainly on the end-effector, damping mainly on the
    (collocated) rotor velocity — chosen by a pole scan of the linearised loop with the
    delay and velocity filter (all closed-loop poles with damping ratio ≈ 0.8, slowest
    ≈ 15 rad/s). On the rig the end-effector follows the smoothed steps with some lag and
    overshoot (friction on the rotor is 40 torque/c) and the command stays within a few
    hundred units, the scale of the report's Fig. 4.12. Setting ``kp1 = kd1 = 0`` gives a
    classic collocated rotor PD. The reference is :func:`smoothed_steps` unless
    ``reference`` (and ``reference_rate``, default 0) are given; ``u_limit`` optionally
    saturates the command.
    """

    kp1: float = 500.0
    kd1: float = 60.0
    kp2: float = 50.0
    kd2: float = 30.0
    velocity_cutoff_hz: float = 50.0
    reference: Callable[[float], float] | None = None
    reference_rate: Callable[[float], float] | None = None
    u_limit: float | None = None

    def r(self, t):
        return smoothed_steps(t) if self.reference is None else self.reference(t)

    def dr(self, t):
        if self.reference_rate is not None:
            return self.reference_rate(t)
        if self.reference is None:
            return smoothed_steps(t, derivative=True)
        return 0.0

    def command(self, t: float, s_meas: np.ndarray, w: np.ndarray) -> float:
        """Command for time ``t`` from the measured angles ``[s1, s2]`` and velocities ``w``."""
        r, dr = self.r(t), self.dr(t)
        u = (self.kp1 * (r - s_meas[0]) + self.kd1 * (dr - w[0])
             + self.kp2 * (r - s_meas[1]) + self.kd2 * (dr - w[1]))
        if self.u_limit is not None:
            u = min(max(u, -self.u_limit), self.u_limit)
        return float(u)


# =============================================================================== data
@dataclass
class RigData:
    """Rig output sampled at ``t`` (all arrays of shape ``(N+1,)``).

    Measured: ``t``, ``u`` (the commanded motor signal), ``s1``, ``s2`` (encoder readings,
    with quantisation/noise when enabled). True, noise-free: ``s1_true``, ``s2_true``,
    ``v1_true``, ``v2_true``, ``u_applied`` (applied torque/c at the sample instants),
    ``f1_level``, ``f2_level`` (Coulomb levels at the samples; 0 without friction).
    """

    t: np.ndarray
    u: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    s1_true: np.ndarray
    s2_true: np.ndarray
    v1_true: np.ndarray
    v2_true: np.ndarray
    u_applied: np.ndarray
    f1_level: np.ndarray
    f2_level: np.ndarray
    settings: RigSettings
    input_name: str = ""
    extras: dict = field(default_factory=dict)

    MEASURED = ("t", "u", "s1", "s2")

    def __getitem__(self, key: str) -> np.ndarray:
        if key in self.extras:
            return self.extras[key]
        return getattr(self, key)

    def __contains__(self, key: str) -> bool:
        return key in self.extras or (key in {f.name for f in dataclasses.fields(self)})

    def keys(self):
        return [f.name for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)] + list(self.extras)

    @property
    def true_states(self) -> np.ndarray:
        """``(N+1, 4)`` array ``[s1, s2, v1, v2]`` of the noise-free states."""
        return np.stack([self.s1_true, self.s2_true, self.v1_true, self.v2_true], axis=1)

    def measured(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.MEASURED}

    def to_dict(self) -> dict[str, np.ndarray]:
        return {k: self[k] for k in self.keys()}


# =============================================================================== the plant
@dataclass(frozen=True)
class TwoInertia:
    """The one right-hand side of the two-inertia rig, with hooks for its effects.

    Used by :func:`simulate_rig` (friction with slowly varying levels, gain, delay) and by
    :func:`manipulators.rig_effects.simulate_effect_rig` (the diagnosis library's effects).
    With ``x = [s1, s2, v1, v2]`` (sign conventions of the module docstring)::

        m1 v1' =  T_s − fr1
        m2 v2' =  u_app − T_s − fr2,        T_s = elastic(s2 − s1) + b (v2 − v1)

    Hooks (``None`` is the nominal, linear law):

    * ``friction(t, v) -> (fr1, fr2)``: the friction torques of both bodies at time ``t`` and
      velocities ``v = [v1, v2]`` (with the sign of ``v``; subtracted). ``None``: none.
    * ``elastic(d) -> torque``: the spring torque ``k · spring(d)`` of the twist ``d = s2 − s1``.
      ``None``: ``k d``.
    * ``input(u_cmd, t) -> u_app``: the input transformation from the command function
      ``u_cmd`` to the applied torque at ``t`` (gain, delay, saturation, offset …).
      ``None``: ``u_cmd(t)``.

    :meth:`rhs` takes the applied torque itself (a held, piecewise-constant input);
    :meth:`driven` closes the loop over a command function for ``solve_ivp``.
    """

    m1: float
    m2: float
    k: float
    b: float
    friction: Callable[[float, np.ndarray], Any] | None = None
    elastic: Callable[[float], float] | None = None
    input: Callable[[Callable[[float], float], float], float] | None = None

    def applied(self, u_cmd: Callable[[float], float], t: float) -> float:
        """The applied torque at ``t`` for the command function ``u_cmd``."""
        return u_cmd(t) if self.input is None else self.input(u_cmd, t)

    def rhs(self, t, x, u_app) -> np.ndarray:
        """``x'`` at time ``t`` under the applied torque ``u_app``."""
        s1, s2, v1, v2 = x
        d = s2 - s1
        spring = (self.k * d if self.elastic is None else self.elastic(d)) + self.b * (v2 - v1)
        fr1, fr2 = (0.0, 0.0) if self.friction is None else self.friction(t, x[2:])
        return np.array([v1, v2, (spring - fr1) / self.m1, (u_app - spring - fr2) / self.m2])

    def driven(self, u_cmd: Callable[[float], float]) -> Callable[[float, np.ndarray], np.ndarray]:
        """``f(t, x)``: the right-hand side driven by the command function ``u_cmd``."""
        def f(t, x):
            return self.rhs(t, x, self.applied(u_cmd, t))
        return f


# =============================================================================== simulator
class _Rig:
    """The rig's :class:`TwoInertia` plant with its effect hooks (``plant``, ``rhs``), and the
    effect bookkeeping of one simulation: random streams, friction levels, encoder model."""

    def __init__(self, st: RigSettings):
        self.st = st
        ss = np.random.SeedSequence(st.seed)
        fric_ss, noise_ss, unoise_ss = ss.spawn(3)
        rng = np.random.default_rng(fric_ss)
        lo, hi = st.friction_variation_freq
        self.var_freq = rng.uniform(lo, hi, size=2)
        self.var_phase = rng.uniform(0.0, TWO_PI, size=2)
        self.noise_rng = np.random.default_rng(noise_ss)
        self.unoise_rng = np.random.default_rng(unoise_ss)
        self._f0 = np.array([st.f1, st.f2], dtype=float)
        self._vs = np.array([st.v_s1, st.v_s2], dtype=float)
        gain, delay = st.effective_gain, st.effective_delay

        def applied(u_cmd, t):  # u_cmd is 0 for t < 0 (see _command_function)
            return gain * u_cmd(t - delay)

        self.plant = TwoInertia(st.m1, st.m2, st.k, st.b,
                                friction=self.friction if st.friction else None, input=applied)
        self.rhs = self.plant.rhs

    def levels(self, t):
        """Coulomb levels ``(f1(t), f2(t))``, stacked along the first axis (shape
        ``(2,) + t.shape``); zeros without friction."""
        st = self.st
        t = np.asarray(t, dtype=float)
        shape = (2,) + (1,) * t.ndim
        if not st.friction:
            return np.zeros(shape[:1] + t.shape)
        f0 = self._f0.reshape(shape)
        if not st.friction_variation:
            return f0 + np.zeros(t.shape)
        a = st.friction_variation_amplitude
        return f0 * (1.0 + a * np.sin(TWO_PI * self.var_freq.reshape(shape) * t
                                      + self.var_phase.reshape(shape)))

    def friction(self, t, v):
        """The friction hook: smooth Coulomb on both bodies in one call, at the levels of ``t``."""
        return smooth_coulomb(v, self.levels(t), self._vs)

    def measure(self, s_true):
        st = self.st
        s = np.array(s_true, dtype=float, copy=True)
        if st.noise and st.noise_std > 0:
            s = s + self.noise_rng.normal(0.0, st.noise_std, size=s.shape)
        if st.quantization:
            q = st.quantization_step
            s = q * np.round(s / q)
        return s


def _command_function(inp, t_samples: np.ndarray):
    """Return ``(u_cmd, samples, name, knots)``: the continuous command ``u_cmd(t)``
    (``0`` for ``t < 0``), its values at ``t_samples``, a name, and the times where a
    sampled (linearly interpolated) input has kinks (``None`` for callables)."""
    if isinstance(inp, str):
        if inp != "sweep":
            raise ValueError(f"unknown input {inp!r} (use 'sweep', 'pd', a callable or an array)")
        fn, name = sine_sweep, "sweep"
    elif callable(inp):
        fn, name = inp, getattr(inp, "__name__", "callable")
    else:
        if isinstance(inp, tuple) and len(inp) == 2:
            t_in, u_in = (np.asarray(a, dtype=float) for a in inp)
        else:
            u_in = np.asarray(inp, dtype=float)
            if u_in.shape != t_samples.shape:
                raise ValueError(
                    f"array input must have one value per sample ({t_samples.size}), got {u_in.shape}; "
                    "or pass a (t, u) tuple")
            t_in = t_samples

        def u_cmd(t, _t=t_in, _u=u_in):
            return 0.0 if t < 0.0 else float(np.interp(t, _t, _u))

        return u_cmd, np.interp(t_samples, t_in, u_in), "array", t_in

    def u_cmd(t, _fn=fn):
        return 0.0 if t < 0.0 else float(_fn(t))

    return u_cmd, np.array([u_cmd(tt) for tt in t_samples]), name, None


def simulate_rig(settings: RigSettings | None = None, input: Any = "sweep", duration: float = 1.0,
                 controller: PDController | None = None) -> RigData:
    """Simulate the rig and return measured + true data at ``sample_rate`` on ``[0, duration]``.

    ``input``: ``"sweep"`` (:func:`sine_sweep` with defaults), ``"pd"`` (closed-loop PD
    tracking, see :class:`PDController`), a callable ``u(t)`` of continuous time, an array
    with one command value per sample, or a ``(t, u)`` tuple (linearly interpolated).

    How the command becomes the applied torque ``u_app``:

    * ``zoh`` on (and always for ``"pd"``): command ``u_k`` (taken at ``t_k``) is applied as
      ``gain * u_k`` on ``[t_k + delay, t_{k+1} + delay)``; integrated segment by segment;
    * ``zoh`` off, callable input: ``u_app(t) = gain * u(t - delay)``, one integration;
    * ``zoh`` off, array input: linear interpolation of the samples, integrated segment by
      segment between the (delayed) kinks so the solver never steps across one.

    The initial state is ``settings.initial_state`` (at rest by default) and the command is
    0 before ``t = 0``.
    """
    st = settings if settings is not None else RigSettings()
    rig = _Rig(st)
    fs = float(st.sample_rate)
    n = int(round(duration * fs))
    t_samples = np.arange(n + 1) / fs
    t_end = t_samples[-1]
    gain, delay = st.effective_gain, st.effective_delay
    x0 = np.asarray(st.initial_state, dtype=float)
    solver = dict(method=st.method, rtol=st.rtol, atol=st.atol)

    closed_loop = isinstance(input, str) and input == "pd"
    knots = None
    if closed_loop:
        ctrl = controller if controller is not None else PDController()
        name = "pd"
        u_cmd = None
        u_samples = np.zeros(n + 1)
    else:
        u_cmd, u_samples, name, knots = _command_function(input, t_samples)
    held = closed_loop or st.zoh

    states = np.zeros((n + 1, 4))
    s_meas = np.zeros((n + 1, 2))

    if not held and knots is None:
        # smooth callable: one continuous integration, delayed command evaluated exactly
        sol = solve_ivp(rig.plant.driven(u_cmd), (0.0, t_end), x0, t_eval=t_samples, max_step=1.0 / fs, **solver)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(f"rig integration failed: {sol.message}")
        states = sol.y.T.copy()
        s_meas = rig.measure(states[:, :2])
    else:
        # events (time, kind, k): kind 0 = sample k is taken (and, closed loop, command k
        # computed); kind 1 = command k starts to act (held input); kind 2 = a kink of the
        # interpolated array input reaches the motor (no action, just a segment boundary).
        events = [(t_samples[k], 0, k) for k in range(n + 1)]
        if held:
            events += [(t_samples[k] + delay, 1, k) for k in range(n + 1)
                       if t_samples[k] + delay < t_end]
        else:
            events += [(tk + delay, 2, j) for j, tk in enumerate(knots) if 0.0 < tk + delay < t_end]
        events.sort()
        x = x0.copy()
        t_cur = 0.0
        ua = 0.0
        if held:
            def f(t, y):
                return rig.rhs(t, y, ua)
        else:
            f = rig.plant.driven(u_cmd)
        if closed_loop:
            a_filt = math.exp(-TWO_PI * ctrl.velocity_cutoff_hz / fs)
            w = np.zeros(2)
            s_prev = None
        eps = 1e-9 / fs
        for te, kind, k in events:
            if te > t_cur + eps:
                sol = solve_ivp(f, (t_cur, te), x, **solver)
                if not sol.success:  # pragma: no cover
                    raise RuntimeError(f"rig integration failed: {sol.message}")
                x = sol.y[:, -1].copy()
                t_cur = te
            if kind == 0:
                states[k] = x
                s_meas[k] = rig.measure(x[:2])
                if closed_loop:
                    sm = s_meas[k]
                    if s_prev is not None:
                        w = a_filt * w + (1.0 - a_filt) * (sm - s_prev) * fs
                    s_prev = sm.copy()
                    u_samples[k] = ctrl.command(t_samples[k], sm, w)
            elif kind == 1:
                ua = gain * u_samples[k]

    # applied torque at the sample instants (right-continuous for a held input)
    if held:
        j = np.floor((t_samples - delay) * fs + 1e-6).astype(int)
        u_applied = np.where(j >= 0, gain * u_samples[np.clip(j, 0, n)], 0.0)
    else:
        u_applied = np.array([rig.plant.applied(u_cmd, tt) for tt in t_samples])

    u_meas = u_samples.copy()
    if st.noise and st.u_noise_std > 0:
        u_meas = u_meas + rig.unoise_rng.normal(0.0, st.u_noise_std, size=u_meas.shape)
    f1l, f2l = rig.levels(t_samples)
    return RigData(
        t=t_samples,
        u=u_meas,
        s1=s_meas[:, 0].copy(),
        s2=s_meas[:, 1].copy(),
        s1_true=states[:, 0].copy(),
        s2_true=states[:, 1].copy(),
        v1_true=states[:, 2].copy(),
        v2_true=states[:, 3].copy(),
        u_applied=u_applied,
        f1_level=np.broadcast_to(f1l, t_samples.shape).copy(),
        f2_level=np.broadcast_to(f2l, t_samples.shape).copy(),
        settings=st,
        input_name=name,
    )


def pd_validation_input(settings: RigSettings | None = None, duration: float = 1.0,
                        controller: PDController | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The validation command signal: simulate the PD loop closed on the rig and return
    ``(t, u)`` — the commands the controller produced. ``u`` can be replayed open-loop
    (array input) on a model or on the rig."""
    data = simulate_rig(settings, input="pd", duration=duration, controller=controller)
    return data.t, data.u


# =============================================================================== mass–spring–damper
def msd_input(t):
    """Default input for the mass–spring–damper example (report §3.4; the report's figure is
    unreadable, so this is our choice): a three-tone multisine around the natural frequency
    1 rad/s, ``sin(0.5 t) + 0.6 sin(1.3 t + 1) + 0.3 sin(2.9 t + 2)``, which excites mass,
    damping and stiffness terms alike on [0, 10]."""
    t = np.asarray(t, dtype=float)
    out = np.sin(0.5 * t) + 0.6 * np.sin(1.3 * t + 1.0) + 0.3 * np.sin(2.9 * t + 2.0)
    return float(out) if out.ndim == 0 else out


def msd_data(t=None, m: float = 1.0, b: float = 1.0, k: float = 1.0, input: Any = None,
             noise: float = 0.0, u_noise: float = 0.0, seed: int = 0,
             initial_state: tuple[float, float] = (0.0, 0.0)) -> dict[str, np.ndarray]:
    """Data for ``m a + b v + k s = u`` (report §3.4, DESIGN §3).

    ``t`` defaults to 1001 points on [0, 10]; ``input`` is a callable ``u(t)``, an array on
    ``t`` (linearly interpolated) or ``None`` for :func:`msd_input`. Gaussian noise of std
    ``noise`` is added to ``s`` and ``u_noise`` to ``u`` (seeded). Returns a dict with the
    measured columns ``t, u, s`` and the true ``s_true, v_true, a_true, u_true``.
    """
    t = np.linspace(0.0, 10.0, 1001) if t is None else np.asarray(t, dtype=float)
    if input is None:
        ufun = msd_input
    elif callable(input):
        ufun = input
    else:
        u_arr = np.asarray(input, dtype=float)

        def ufun(tt, _u=u_arr):
            return np.interp(tt, t, _u)

    def f(tt, x):
        return [x[1], (float(ufun(tt)) - b * x[1] - k * x[0]) / m]

    sol = solve_ivp(f, (t[0], t[-1]), list(initial_state), t_eval=t, method="DOP853",
                    rtol=1e-12, atol=1e-13, max_step=(t[-1] - t[0]) / 200)
    if not sol.success:  # pragma: no cover
        raise RuntimeError(sol.message)
    s_true, v_true = sol.y
    u_true = np.array([float(ufun(tt)) for tt in t])
    a_true = (u_true - b * v_true - k * s_true) / m
    rng = np.random.default_rng(seed)
    s = s_true + (rng.normal(0.0, noise, size=t.shape) if noise > 0 else 0.0)
    u = u_true + (rng.normal(0.0, u_noise, size=t.shape) if u_noise > 0 else 0.0)
    return dict(t=t, u=u, s=s, s_true=s_true, v_true=v_true, a_true=a_true, u_true=u_true)


def msd_noisy_data(level: float = 0.01, seed: int = 0, **options) -> dict[str, np.ndarray]:
    """:func:`msd_data` with "``level`` noise" as the studies use it: Gaussian noise of std
    ``level`` × the RMS of the true s on s and ``level`` × the RMS of the true u on u."""
    clean = msd_data(**options)
    rms_s, rms_u = (float(np.sqrt(np.mean(clean[c] ** 2))) for c in ("s_true", "u_true"))
    return msd_data(noise=level * rms_s, u_noise=level * rms_u, seed=seed, **options)


# =============================================================================== CSV
def save_csv(path, data, columns: Sequence[str] | None = None) -> Path:
    """Write measured columns to CSV with a one-line header (default ``t,u,s1,s2`` for rig
    data, ``t,u,s`` for mass–spring–damper data). Values use 17 significant digits, so a
    round trip is lossless."""
    from shootlab.estimation.data import write_table
    if columns is None:
        columns = ("t", "u", "s1", "s2") if "s1" in data else ("t", "u", "s")
    return write_table(path, data, columns)


def load_csv(path) -> dict[str, np.ndarray]:
    """Read a CSV written by :func:`save_csv` into ``{column name: array}`` (through
    :func:`shootlab.estimation.data.read_table`, the one CSV reader)."""
    from shootlab.estimation.data import read_table
    m = read_table(path)
    return {"t": m.t, **m.channels}
