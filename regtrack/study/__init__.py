"""Studies at scale: parametric sweeps, cohorts and calibration, locally or on Dask.

* :func:`regtrack.study.spec.load_study` reads and validates a study TOML -> ``Study``;
* :func:`regtrack.study.run.run_study` runs it and writes ``table.csv``, ``summary.json``,
  Figure-8 plots and ``study.pdf``;
* :class:`regtrack.study.engine.Engine` executes :class:`~regtrack.study.runner.RunSpec`
  lists with the per-run result cache, shared-work scheduling and retries;
* :func:`regtrack.study.calibrate.calibrate` finds c1 / nu (/ friction) for a case.

Parameter names and the overrides they set: :mod:`regtrack.study.params`.
"""

__all__ = ["calibrate", "engine", "params", "plots", "results", "run", "runner", "spec"]
