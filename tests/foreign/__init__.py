"""The foreign measurement generator: CTR "measurements" made by code ctrplan did not write.

Imports nothing from ctrplan: its own robot YAML parsing (yaml.safe_load), its own mechanics
(rigid closed-form arcs; torsionally compliant Cosserat rods with gravity and tip loads, batched
shooting in numpy), its own effect forms (tests/foreign/effects.py), noise, experiment designs and
CSV writer. API: /work/coord/GENERATOR_API.md and README.md here.

    from tests.foreign import generate, generate_study, backbones, ForeignData
    from tests.foreign.scenarios import real_robot     # a realistic truth robot (its docstring)
    from tests.foreign.continuation import continue_path, stability, is_stable, equilibria
    from tests.foreign.folds import bistable_range, fold_crossing_pairs, fold_crossing_cases

The continuation oracle (continuation.py, folds.py, energy.py; README.md) replays a joint motion
as the physical robot would: it follows its equilibrium branch and snaps where that branch ends,
with equilibria and a stability measure from an elastic energy discretised here by finite
elements.

Its effect forms are deliberately OUTSIDE ctrplan's fitted families (tests/foreign/effects.py
docstring and README.md say, per effect, why ctrplan's family of the same name cannot represent
it; tests/test_foreign_generator.py checks the best fit of that family leaves a residual).

Mean / max tip displacement (mm) each effect causes at its DEFAULT parameters against the same
rows without it (design "sweeps", n=1000, seed=1, no noise; measured 2026-11-27 with the forms
of issue 36, each outside what ctrplan's families can combine):

    effect                    seed1 mean/max    two_tube_nylon mean/max
    torsion (GJ, couplings,      3.12 / 8.28       17.27 / 63.19
             play)
    clearance (crossing)         4.68 / 10.91       1.76 / 7.29
    friction end_moment          4.65 / 18.42       1.60 / 8.64
    friction coulomb_lag         3.93 / 9.85        7.88 / 19.90
    friction presliding          4.53 / 37.22       7.19 / 41.52
    friction stick_slip          3.71 / 10.13       7.53 / 20.95
    precurvature (ramp, twist,   5.12 / 12.01       8.13 / 18.53
                  relaxation)
    stiffness (softening)        9.59 / 15.96       3.55 / 8.52
    load (gravity, tip force,    4.64 / 13.60       7.89 / 20.11
          filled lumen, tether,
          compliant mount, wall)
    joint_offset                 3.14 / 5.07        4.06 / 11.30
    registration (+ scale, coil, 5.38 / 9.14        5.50 / 9.45
                  housing)
    distortion (bumps)           1.77 / 3.60        0.93 / 3.74
    distortion (dipole)          0.57 / 3.11        0.65 / 11.62
    drift                        3.23 / 5.06        3.23 / 5.06

Torsion uses the tubes' physical GJ = E J / (2 (1 + nu)) times ``gj_scale`` per tube; it is
small on seed1 and large on the nylon pair. Friction is only visible where rows carry a
direction of motion (not in "uniform").
"""

from .core import (
                       STUDY_EFFECTS,
                       STUDY_EXPERIMENTS,
                       ForeignData,
                       backbones,
                       generate,
                       generate_study,
                       read_csv,
                       truth,
)
from .designs import DESIGNS
from .effects import FRICTION_FORMS, OUTSIDE_EFFECTS, VOCAB_EFFECTS
from .robot import load_spec, valid

__all__ = ["generate", "generate_study", "STUDY_EFFECTS", "STUDY_EXPERIMENTS", "backbones", "ForeignData", "VOCAB_EFFECTS",
           "OUTSIDE_EFFECTS", "FRICTION_FORMS", "DESIGNS", "read_csv", "load_spec", "valid", "truth"]
