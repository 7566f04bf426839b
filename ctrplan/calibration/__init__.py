"""Calibration: measured data, residual evidence, effect selection and reports.

``ctrplan diagnose`` (:func:`ctrplan.calibration.diagnose.diagnose`) is a pipeline of named
stages, one module each, each returning a frozen dataclass; no stage imports a later one:

1. :mod:`~ctrplan.calibration.data`      data checks and the fit / validation / test split
   (the one held-out splitter of diagnose, ``--best`` and train: :mod:`ctrplan.split`)
2. :mod:`~ctrplan.calibration.evidence`  data-only tests (noise floor, hysteresis, harmonics ...)
3. :mod:`~ctrplan.calibration.select`    screening and selection of effects (forward, joint)
4. :mod:`~ctrplan.calibration.fit`       the final refit on fit + validation rows
   (:mod:`~ctrplan.calibration.nuisance`: drift / field nuisances, tested after the fit)
5. :mod:`~ctrplan.calibration.verdict`   what is named, status, unexplained remainder
6. :mod:`~ctrplan.calibration.report`    report.json / report.md / plots / models, as one set

Beside them: :mod:`~ctrplan.calibration.result` (the typed public result, ``DiagnoseReport``),
:mod:`~ctrplan.calibration.lsq` (the least-squares engine of stages 3 and 4),
:mod:`~ctrplan.calibration.binned` (the report's descriptive binned statistics),
:mod:`~ctrplan.calibration.residual` (the optional learned residual),
:mod:`~ctrplan.calibration.confound` (effects the rows cannot tell apart),
:mod:`~ctrplan.calibration.best` (``diagnose --best``), :mod:`~ctrplan.calibration.simulate`
(simulated measurements).
"""
