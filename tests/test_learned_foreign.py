"""The learned model on shape data from the independent (foreign) generator, issue 14.

The generator (tests/foreign, no ctrplan code) makes seed1 "measurements" with clearance, a
precurvature error and direction-dependent friction (the study's end-moment form), 0.3 mm noise
per axis on every backbone point, from continuous back-and-forth sweeps. Per seed: 1,500 rows in
10 sweeps of 150; 3 whole sweeps (450 rows) are held out for testing, 1 sweep is the validation
set for early stopping and 6 sweeps (900 rows) are the fine-tuning set: 1,050 fine-tuning
shapes in all. The directions the direction-aware models get are recovered from the row order
(:func:`direction_from_rows`), not taken from the generator.

Sim = the shipped seed1 model (trained on 100,000 simulated physics shapes). Sim+Real variants:
pure (fine-tuned), direction-aware (fine-tuned with direction inputs added), residual (a new
network learning the difference to the Sim model) and residual + direction. Metric: mean over
the held-out configurations of the max deviation along the shaft (20 points, against the noisy
measured points, as in the literature), physics = the torsionally compliant model.

``experiment`` is also what ``benchmarks/bench_learned_foreign.py`` runs at full size.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from ctrplan.robot import load_robot
from ctrplan.shape import training as T
from ctrplan.shape.base import direction_from_rows
from ctrplan.shape.learned import default_model_for
from ctrplan.shape.physics import PhysicsModel

#: Pinned (the generator's defaults on 2026-11-23), so retuned defaults do not move the figures
#: (the parts added to the generator's forms later are off: a smooth clearance crossing, no
#: pre-twist or relaxation, the contact term of 2026-11-23).
EFFECTS = {"clearance": {"amplitude": 0.065, "phase_deg": 205.0, "harmonics": [0.5, 0.5],
                         "snap": 0.0},
           "precurvature": {"scale": [0.92, 1.10, 0.93], "twist": 0.0, "relax": 0.0},
           "friction": {"form": "end_moment", "mu": 0.08, "contact": 12.0}}
NOISE_MM = 0.3
SEEDS = range(10)
#: The done-when: the best Sim+Real variant at least this much better than physics (mean over seeds).
MIN_GAIN = 0.40


def foreign_data(seed: int, n_rows: int = 1500) -> T.ShapeData:
    """Foreign seed1 sweeps as ShapeData; directions recovered from the row order."""
    from tests.foreign import generate

    d = generate(robot="seed1", design="sweeps", n=n_rows, effects=EFFECTS, noise_mm=NOISE_MM,
                 seed=seed, points=20)
    sweep = np.asarray(d.sweep).astype(str)
    return T.ShapeData(np.asarray(d.q, dtype=float), np.asarray(d.points, dtype=float),
                       source=f"foreign:seed1:sweeps:n={n_rows}:seed={seed}",
                       direction=direction_from_rows(d.q, sweep), sweep=sweep)


def split_sweeps(data: T.ShapeData, seed: int, test: int = 3, val: int = 1):
    """Held-out whole sweeps: ``test`` sweeps for testing, ``val`` for validation, the rest
    for training (seeded choice)."""
    ids = np.unique(data.sweep)
    order = np.random.default_rng(1000 + seed).permutation(ids)
    te, va = set(order[:test]), set(order[test:test + val])
    pick = lambda s: data.subset(np.flatnonzero(np.isin(data.sweep, list(s))))  # noqa: E731
    return pick(set(ids) - te - va), pick(va), pick(te)


def experiment(seed: int, n_rows: int = 1500, variants=T.VARIANTS, epochs: int = 300,
               width: int = 30, depth: int = 3) -> dict:
    """Physics and the Sim+Real variants on one foreign data set; mean max deviation (mm)."""
    r = load_robot("seed1")
    sim = default_model_for(r)
    data = foreign_data(seed, n_rows)
    tr, va, te = split_sweeps(data, seed)
    fine = T.TrainConfig(epochs=epochs, lr=5e-4, batch_size=128, patience=20, seed=seed, progress=False)
    real_only = T.TrainConfig(epochs=epochs, lr=2e-3, batch_size=128, patience=20, seed=seed, progress=False)
    out = {"seed": seed, "rows": [len(tr), len(va), len(te)],
           "physics": T.evaluate(PhysicsModel(r), te)["max_dev_mean"],
           "sim": T.evaluate(sim, te)["max_dev_mean"], "variants": {}, "seconds": {}}
    for v in variants:
        t0 = time.perf_counter()
        model, _ = T.fit_real(r, tr, va, v, sim_model=sim, width=width, depth=depth, seed=seed,
                              fine=fine, real_only=real_only, refit=True)
        out["variants"][v] = T.evaluate(model, te)["max_dev_mean"]
        out["seconds"][v] = time.perf_counter() - t0
    return out


def test_directions_from_row_order_equal_the_generators_truth():
    from tests.foreign import generate

    d = generate(robot="seed1", design="sweeps", n=600, effects=EFFECTS, noise_mm=NOISE_MM, seed=3)
    np.testing.assert_array_equal(direction_from_rows(d.q, np.asarray(d.sweep)), d.direction)


@pytest.mark.statistical
def test_best_sim_plus_real_variant_beats_physics_by_40_percent_over_10_seeds():
    """10 seeds at the size of the module docstring (full size; 300 epochs with early
    stopping). Threshold: the best Sim+Real variant (by mean over seeds) has a mean max
    deviation <= 0.6 x physics in the mean over the 10 seeds, and beats physics in every seed."""
    torch.set_num_threads(1)
    variants = ("pure", "residual+direction")
    runs = [experiment(s, variants=variants) for s in SEEDS]
    phys = np.array([r["physics"] for r in runs])
    per = {v: np.array([r["variants"][v] for r in runs]) for v in variants}
    best = min(per, key=lambda v: per[v].mean())
    gain = 1 - per[best].mean() / phys.mean()
    msg = f"physics {phys.mean():.3f}, " + ", ".join(f"{v} {a.mean():.3f}" for v, a in per.items())
    assert gain >= MIN_GAIN, msg
    assert np.all(per[best] < phys), msg


#: The done-when of issue 19: ``train`` without variant flags within this factor of the best
#: variant (mean over seeds of the held-out mean max deviation).
AUTO_WITHIN = 1.10
AUTO_SEEDS = range(5)


def auto_experiment(seed: int, n_rows: int = 1500, epochs: int = 300) -> dict:
    """What ``ctrplan train --init learned --real CSV`` does without variant flags (automatic
    choice on the validation sweep) next to each variant given explicitly (``--variant V``,
    residual over physics in both), all with the same splits (pretrain_finetune: 80/10/10 by
    whole sweeps) and evaluated on the same held-out test sweeps, never seen by the choice."""
    r = load_robot("seed1")
    sim = default_model_for(r)
    data = foreign_data(seed, n_rows)
    fine = T.TrainConfig(epochs=epochs, lr=5e-4, batch_size=128, patience=20, seed=seed, progress=False)
    real_only = T.TrainConfig(epochs=epochs, lr=2e-3, batch_size=128, patience=20, seed=seed, progress=False)
    kw = dict(seed=seed, fine=fine, real_only=real_only, base=sim, residual_base=PhysicsModel(r))
    _, _, te = T.split(data, seed=seed + 1)
    out = {"seed": seed, "physics": T.evaluate(PhysicsModel(r), te)["max_dev_mean"], "variants": {}}
    t0 = time.perf_counter()
    model, rep = T.pretrain_finetune(r, None, data, variant="auto", **kw)
    out["auto_seconds"] = time.perf_counter() - t0
    out["auto"] = T.evaluate(model, te)["max_dev_mean"]
    out["chosen"] = rep.variant
    for v in T.VARIANTS:
        m, _ = T.pretrain_finetune(r, None, data, variant=v, **kw)
        out["variants"][v] = T.evaluate(m, te)["max_dev_mean"]
    return out


@pytest.mark.statistical
def test_train_without_variant_flags_is_within_10_percent_of_the_best_variant():
    """5 seeds at full size (1,500 rows in 10 sweeps; 8 training, 1 validation, 1 test sweep):
    the automatically chosen variant's mean max deviation on the test sweeps, averaged over
    the seeds, is at most 1.10 x that of the best variant given explicitly (the best by the
    same average), and it beats physics in every seed."""
    torch.set_num_threads(1)
    runs = [auto_experiment(s) for s in AUTO_SEEDS]
    auto = np.array([r["auto"] for r in runs])
    per = {v: np.array([r["variants"][v] for r in runs]) for v in T.VARIANTS}
    best = min(per, key=lambda v: per[v].mean())
    msg = (f"auto {auto.mean():.3f} (chose {[r['chosen'] for r in runs]}), "
           + ", ".join(f"{v} {a.mean():.3f}" for v, a in per.items()))
    assert auto.mean() <= AUTO_WITHIN * per[best].mean(), msg
    assert np.all(auto < np.array([r["physics"] for r in runs])), msg
