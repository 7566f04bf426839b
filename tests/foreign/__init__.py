"""The foreign measurement generator: CTR "measurements" made by code ctrplan did not write.

Imports nothing from ctrplan: its own robot YAML parsing (yaml.safe_load), its own mechanics
(rigid closed-form arcs; torsionally compliant Cosserat rods with gravity and tip loads, batched
shooting in numpy), its own effect forms (tests/foreign/effects.py), noise, experiment designs and
CSV writer. API: /work/coord/GENERATOR_API.md.

    from tests.foreign import generate, generate_study, backbones, ForeignData
"""

from .designs import DESIGNS
from .effects import FRICTION_FORMS, OUTSIDE_EFFECTS, VOCAB_EFFECTS
from .core import (STUDY_EFFECTS, STUDY_EXPERIMENTS, ForeignData, backbones, generate,
                       generate_study, read_csv, truth)
from .robot import load_spec, valid

__all__ = ["generate", "generate_study", "backbones", "ForeignData", "VOCAB_EFFECTS",
           "OUTSIDE_EFFECTS", "FRICTION_FORMS", "DESIGNS", "read_csv", "load_spec", "valid", "truth"]
