"""Independently written data simulators for the diagnosis benchmark: another integrator and
discretisation, noise model, magnitudes and inputs than the packages' own generators.

* :mod:`.rig` — the flexible two-inertia manipulator with one mechanical effect;
* :mod:`.mixture` — the confined-compression test with one mixture effect;
* :mod:`.duffing` — a Duffing oscillator (hardening spring, an input offset in every record),
  diagnosed with the linear mass–spring–damper;
* :mod:`.tanks` — two cascaded tanks with an overflowing upper tank and a clipping level sensor,
  diagnosed with ``examples/tanks.py``.

Each has ``data(effect, magnitude, noise, seed) -> (identification, validation, info)`` (the
benchmark's records) and ``simulate(effect, magnitude, input_t, input_u, noise, seed) ->
Measurements`` (the same system under any input given by its samples, e.g. a discriminating
experiment); ``INPUT`` names the input channel.  :mod:`.rig` and :mod:`.mixture` also hold
look-alike pairs (``LOOKALIKES``, the magnitude ``"lookalike"``)."""
