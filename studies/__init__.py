"""Studies on top of shootlab: shooting-point sweeps (serial or Dask distributed), stiffness from
local-Jacobian eigenvalues, checks of :func:`shootlab.suggest_shooting_points`, and time/memory
scaling of a Newton iteration; plus the report's reproductions (``studies.msd_report``, …).

Command line: ``python -m studies {sweep, stiffness, suggest, scaling} -h``.
"""
