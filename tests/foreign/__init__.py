"""The foreign measurement generator: CTR "measurements" made by code ctrplan did not write.

Imports nothing from ctrplan: its own robot YAML parsing (yaml.safe_load), its own mechanics
(rigid closed-form arcs; torsionally compliant Cosserat rods with gravity and tip loads, batched
shooting in numpy), its own effect forms (tests/foreign/effects.py), noise, experiment designs and
CSV writer. API: /work/coord/GENERATOR_API.md.

    from tests.foreign import generate, generate_study, backbones, ForeignData

Mean / max tip displacement (mm) each effect causes at its DEFAULT parameters against the same
rows without it (design "sweeps", n=1000, seed=1, no noise; measured 2026-11-23):

    effect                    seed1 mean/max    two_tube_nylon mean/max
    torsion (physical GJ)        0.90 / 3.32       12.73 / 37.32
    clearance                    3.84 / 9.45        1.25 / 5.90
    friction end_moment          1.37 / 7.30        3.47 / 20.26
    friction coulomb_lag         1.32 / 3.38        2.65 / 6.04
    friction presliding          1.22 / 3.76        2.35 / 7.12
    precurvature                 1.77 / 4.77        5.09 / 11.53
    stiffness                    3.07 / 4.88        2.41 / 4.15
    load (gravity + tip force)   3.42 / 10.43       3.48 / 9.69
    joint_offset                 1.88 / 3.13        3.23 / 7.05
    registration                 3.60 / 5.30        3.52 / 4.47
    distortion                   2.31 / 3.41        2.49 / 3.43
    drift                        2.00 / 4.00        2.00 / 4.00

Torsion uses the tubes' physical GJ = E J / (2 (1 + nu)); it is small on seed1 and large on the
nylon pair (pass {"torsion": {"gj_scale": g}} to change it). Friction is only visible where rows
carry a direction of motion (not in "uniform").
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
