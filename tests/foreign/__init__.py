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
rows without it (design "sweeps", n=1000, seed=1, no noise; measured 2026-11-25, load and drift
2026-11-27):

    effect                    seed1 mean/max    two_tube_nylon mean/max
    torsion (GJ, couplings)      1.40 / 4.83       14.89 / 44.31
    clearance                    4.10 / 8.52        1.53 / 6.53
    friction end_moment          2.52 / 9.82        1.45 / 8.14
    friction coulomb_lag         1.31 / 3.75        1.89 / 5.56
    friction presliding          1.16 / 3.99        1.53 / 18.10
    precurvature                 2.72 / 7.26        7.48 / 15.94
    stiffness                    2.49 / 4.43        1.18 / 3.22
    load (gravity, tip force,    4.61 / 13.60       7.83 / 17.98
          filled lumen, tether,
          compliant mount)
    joint_offset                 3.04 / 4.15        3.97 / 9.67
    registration (+ scale)       5.37 / 7.79        5.33 / 6.87
    distortion                   1.58 / 3.21        0.83 / 3.34
    drift                        3.27 / 4.17        3.27 / 4.17

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
