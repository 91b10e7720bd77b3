"""Independently written data simulators for the diagnosis benchmark (issue 15, item 8): another
integrator and discretisation, noise model, magnitudes and inputs than the packages' own generators."""
