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

All randomness comes from ``numpy.random.SeedSequence(seed)`` with separate child streams for
the friction variation and the noise, so switching one effect does not change the other.

Inputs
------
* :func:`sine_sweep`: linear chirp 4 → 14 Hz over 1 s (bracketing both the model's 7.65 Hz
  and the report's 8.5 Hz), amplitude 150 (torque/c units). ``(f0 + f1) T / 2 = 9`` whole
  cycles, so the signal is 0 at both ends. With friction on, this gives angles of about
  -0.15 … 0.8 rad, rotor speeds of ~9 rad/s rms and end-effector speeds of ~1 rad/s rms,
  well above the friction transition most of the time (the report's figure 4.3 axes show a
  command scale of ~100 and angles up to ~1 rad).
* ``"pd"``: closed-loop validation signal — a discrete PD controller (1 kHz, on the
  measured rotor angle, filtered-difference velocity) follows smoothed steps of the
  reference; the torque it commands is the recorded ``u``. See :class:`PDController`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from .friction import smooth_coulomb, smooth_sign

__all__ = [
    "RigSettings",
    "RigData",
    "PDController",
    "eigenfrequency_hz",
    "linear_system_matrices",
    "sine_sweep",
    "smoothed_steps",
    "pd_validation_input",
    "simulate_rig",
    "msd_input",
    "msd_data",
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
        kw = dict(
            friction=True,
            v_s1=v_s1,
            v_s2=v_s2,
            friction_variation=False,
            gain_error=False,
            delay_enabled=False,
            zoh=False,
            quantization=False,
            noise=False,
        )
        kw.update(overrides)
        return cls(**kw)

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
    """Discrete PD position controller on the measured rotor angle (collocated, so stable
    despite the flexible mode), running at the rig's sample rate::

        u_k = kp (r_k - s2_k) + kd (r'_k - w_k),
        w_k = a w_{k-1} + (1 - a) (s2_k - s2_{k-1}) fs,   a = exp(-2 pi f_v / fs)

    (filtered-difference velocity from the encoder). ``u_k`` is held until the next sample.
    The reference is :func:`smoothed_steps` unless ``reference`` / ``reference_rate`` are given.
    ``u_limit`` optionally saturates the command.
    """

    kp: float = 400.0
    kd: float = 40.0
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


# =============================================================================== simulator
class _Rig:
    """Right-hand side and effect bookkeeping for one simulation."""

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

    def levels(self, t):
        st = self.st
        if not st.friction:
            z = np.zeros_like(np.asarray(t, dtype=float))
            return z, z
        t = np.asarray(t, dtype=float)
        if not st.friction_variation:
            return np.full_like(t, st.f1), np.full_like(t, st.f2)
        a = st.friction_variation_amplitude
        f1 = st.f1 * (1.0 + a * np.sin(TWO_PI * self.var_freq[0] * t + self.var_phase[0]))
        f2 = st.f2 * (1.0 + a * np.sin(TWO_PI * self.var_freq[1] * t + self.var_phase[1]))
        return f1, f2

    def rhs(self, t, x, u_app):
        st = self.st
        s1, s2, v1, v2 = x
        spring = st.k * (s2 - s1) + st.b * (v2 - v1)
        if st.friction:
            fl1, fl2 = self.levels(t)
            fr1 = smooth_coulomb(v1, float(fl1), st.v_s1)
            fr2 = smooth_coulomb(v2, float(fl2), st.v_s2)
        else:
            fr1 = fr2 = 0.0
        return np.array([v1, v2, (spring - fr1) / st.m1, (u_app - spring - fr2) / st.m2])

    def measure(self, s_true):
        st = self.st
        s = np.array(s_true, dtype=float, copy=True)
        if st.noise and st.noise_std > 0:
            s = s + self.noise_rng.normal(0.0, st.noise_std, size=s.shape)
        if st.quantization:
            q = st.quantization_step
            s = q * np.round(s / q)
        return s


def _command_function(inp, t_samples: np.ndarray) -> tuple[Callable[[float], float], np.ndarray, str]:
    """Return (continuous command u_cmd(t) with u_cmd = 0 for t < 0, samples at t_samples, name)."""
    if isinstance(inp, str):
        if inp == "sweep":
            fn = sine_sweep
            name = "sweep"
        else:
            raise ValueError(f"unknown input {inp!r} (use 'sweep', 'pd', a callable or an array)")
    elif callable(inp):
        fn = inp
        name = getattr(inp, "__name__", "callable")
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
        name = "array"

        def fn(t, _t=t_in, _u=u_in):
            return float(np.interp(t, _t, _u))

        samples = np.interp(t_samples, t_in, u_in)
        return (lambda t: 0.0 if t < 0.0 else fn(t)), samples, name

    samples = np.array([float(fn(tt)) for tt in t_samples])
    return (lambda t: 0.0 if t < 0.0 else float(fn(t))), samples, name


def simulate_rig(settings: RigSettings | None = None, input: Any = "sweep", duration: float = 1.0,
                 controller: PDController | None = None) -> RigData:
    """Simulate the rig and return measured + true data at ``sample_rate`` on ``[0, duration]``.

    ``input``: ``"sweep"`` (:func:`sine_sweep` with defaults), ``"pd"`` (closed-loop PD
    tracking, see :class:`PDController`), a callable ``u(t)`` of continuous time, an array
    with one command value per sample, or a ``(t, u)`` tuple (linearly interpolated).
    """
    st = settings if settings is not None else RigSettings()
    rig = _Rig(st)
    fs = float(st.sample_rate)
    n = int(round(duration * fs))
    t_samples = np.arange(n + 1) / fs
    gain, delay = st.effective_gain, st.effective_delay
    x0 = np.asarray(st.initial_state, dtype=float)
    solver = dict(method=st.method, rtol=st.rtol, atol=st.atol)

    closed_loop = isinstance(input, str) and input == "pd"
    if closed_loop:
        ctrl = controller if controller is not None else PDController()
        name = "pd"
        u_samples = np.zeros(n + 1)
    else:
        u_cmd, u_samples, name = _command_function(input, t_samples)

    states = np.zeros((n + 1, 4))
    u_applied = np.zeros(n + 1)

    if not closed_loop and not st.zoh:
        # one continuous integration; the delayed command is evaluated exactly (callables) or
        # by linear interpolation (sampled arrays)
        def f(t, x):
            return rig.rhs(t, x, gain * u_cmd(t - delay))

        sol = solve_ivp(f, (0.0, t_samples[-1]), x0, t_eval=t_samples, max_step=1.0 / fs, **solver)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(f"rig integration failed: {sol.message}")
        states = sol.y.T.copy()
        u_applied = np.array([gain * u_cmd(tt - delay) for tt in t_samples])
        s_meas = rig.measure(states[:, :2])
    else:
        # piecewise-constant applied torque: command k (computed at t_k) is applied on
        # [t_k + delay, t_{k+1} + delay); integrate segment by segment between events.
        # events: (time, kind, k) with kind 0 = sample k is taken, kind 1 = command k applied.
        events = [(t_samples[k], 0, k) for k in range(n + 1)]
        events += [(t_samples[k] + delay, 1, k) for k in range(n + 1) if t_samples[k] + delay < t_samples[-1]]
        events.sort()
        x = x0.copy()
        t_cur = 0.0
        ua = 0.0
        s_meas = np.zeros((n + 1, 2))
        if closed_loop:
            a_filt = math.exp(-TWO_PI * ctrl.velocity_cutoff_hz / fs)
            w = 0.0
            s2_prev = None
        eps = 1e-12 / fs
        for te, kind, k in events:
            if te > t_cur + eps:
                sol = solve_ivp(lambda t, y: rig.rhs(t, y, ua), (t_cur, te), x, **solver)
                if not sol.success:  # pragma: no cover
                    raise RuntimeError(f"rig integration failed: {sol.message}")
                x = sol.y[:, -1].copy()
                t_cur = te
            if kind == 0:
                states[k] = x
                u_applied[k] = ua
                s_meas[k] = rig.measure(x[:2])
                if closed_loop:
                    s2m = s_meas[k, 1]
                    if s2_prev is not None:
                        w = a_filt * w + (1.0 - a_filt) * (s2m - s2_prev) * fs
                    s2_prev = s2m
                    tk = t_samples[k]
                    uk = ctrl.kp * (ctrl.r(tk) - s2m) + ctrl.kd * (ctrl.dr(tk) - w)
                    if ctrl.u_limit is not None:
                        uk = float(np.clip(uk, -ctrl.u_limit, ctrl.u_limit))
                    u_samples[k] = uk
            else:
                ua = gain * u_samples[k]
        # u_applied at a sample where an apply-event coincides (delay multiple of 1/fs, or 0)
        # was recorded before the apply event; fix it to the right-continuous value
        for k in range(n + 1):
            j = int(math.floor((t_samples[k] - delay) * fs + 1e-9))
            u_applied[k] = gain * u_samples[j] if j >= 0 else 0.0

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


# =============================================================================== CSV
def save_csv(path, data, columns: Sequence[str] | None = None) -> Path:
    """Write measured columns to CSV with a one-line header (default ``t,u,s1,s2`` for rig
    data, ``t,u,s`` for mass–spring–damper data). Values use 17 significant digits, so a
    round trip is lossless."""
    if columns is None:
        columns = ("t", "u", "s1", "s2") if "s1" in data else ("t", "u", "s")
    cols = [np.asarray(data[c], dtype=float) for c in columns]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(columns),
               comments="", fmt="%.17g")
    return path


def load_csv(path) -> dict[str, np.ndarray]:
    """Read a CSV written by :func:`save_csv` into ``{column name: array}``."""
    path = Path(path)
    with path.open() as fh:
        header = fh.readline().strip()
    names = [h.strip() for h in header.split(",")]
    arr = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {name: arr[:, i].copy() for i, name in enumerate(names)}
