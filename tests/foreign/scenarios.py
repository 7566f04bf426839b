"""A realistic robot for end-to-end tests: several of the generator's forms at once.

    from tests.foreign.scenarios import real_robot
    rr = real_robot(seed=0)                      # seed1 geometry, effects drawn from the seed
    data = rr.measure(n=1000, sweeps=8)          # ForeignData: continuous back-and-forth sweeps
    data.write_csv("measured.csv")               # DESIGN.md measured CSV (configs, tip, time, sweep)
    pts = rr.backbones(q, points=20)             # (N, 20, 3) truth backbones, robot base frame
    pts = rr.backbones(q_path, path=True)        # rows = one continuous motion (hysteresis)

What the truth robot differs in from the nominal robot file (all forms of ``effects.py``, none
exactly representable by ctrplan's families), magnitudes jittered by the seed (+-20 %):

- precurvature: the middle tube ~10 % less curved (and curvature ramps along the sections);
- stiffness: the outer tube ~25 % stiffer in bending (its curved section a little more);
- clearance: a tilt with a second harmonic, a sideways lean and a lateral jump within the gap
  where each outer tube ends;
- friction: the inner tube's rotation lags its command with a presliding hysteresis (Dahl
  exponent 2, ~0.065 rad typical: 0.044 rad growing up to ~1.8x with the part of its curved
  section held inside the middle tube), the outer tubes a little;
- torsion: torsionally compliant tubes with compliant drive couplings;
- tracker noise ``noise_mm`` per axis (default 0.08 mm); optionally a tracker registration
  (``registration=True``: ~2 deg, a few mm, 0.5 % scale) and outliers (``outliers``: fraction of
  rows with a tracker glitch of 3-15 mm).

Seed1 at seed 0: the mean over random configurations of the max deviation along the shaft
between truth and nominal is ~2 mm (``tests/test_foreign_generator.py`` checks 1.5-3 mm).

API (class :class:`RealRobot`):

``measure(n=1000, sweeps=8, points=0, seed=None) -> ForeignData``
    Measured rows from continuous back-and-forth sweeps (all joints moving, reversals in each
    sweep; rows in order of motion, so friction has its history): ``q`` (commanded), ``tip``
    (sensor frame: registration when on, noise, outliers), ``time`` (s), ``sweep``,
    ``points`` (N, points, 3) along the shaft when ``points`` > 0 (same frame, noise), and
    ``tip_clean`` (no noise, no outliers). ``info["outliers"]``: indices of the glitched rows.
``backbones(q, points=20, direction=None, path=False, frame="base") -> (N, points, 3)``
    Noise-free truth backbones, evenly spaced in arc length from the constraint plane to the
    tip. ``path=False``: every row independent; friction uses ``direction`` (N, 2n) in
    {-1, 0, 1} (the direction of each joint's last motion; the settled lag), or none when
    ``direction`` is None. ``path=True``: the rows are one continuous motion in order (the
    hysteresis history builds up along it; directions from the row order). ``frame``: "base"
    (robot frame, for replaying plans) or "sensor" (registration applied). NaN rows: the
    mechanics did not converge (none seen on seed1).
``nominal(q, points=20) -> (N, points, 3)``
    The nominal robot (the robot file, torsionally rigid, no effects), base frame.
``effects``: the generator effect parameters in use (resolved); ``spec``: the robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import effects as E
from .core import ForeignData, generate, truth
from .designs import directions
from .robot import Spec, load_spec


def _jitter(rng, v, rel=0.2):
    """v * (1 + U(-rel, rel)) elementwise (lists or scalars)."""
    a = np.asarray(v, float)
    return (a * (1.0 + rng.uniform(-rel, rel, a.shape))).tolist()


@dataclass
class RealRobot:
    """A truth robot (see the module docstring)."""

    spec: Spec
    effects: dict
    noise_mm: float = 0.08
    outliers: float = 0.0
    seed: int = 0
    info: dict = field(default_factory=dict)

    @property
    def mechanics_effects(self) -> dict:
        return {k: v for k, v in self.effects.items() if k != "registration"}

    def measure(self, n: int = 1000, sweeps: int = 8, points: int = 0,
                seed: int | None = None) -> ForeignData:
        s = self.seed if seed is None else seed
        d = generate(self.spec, "sweeps", n=int(n), effects=self.effects, noise_mm=self.noise_mm,
                     seed=[int(s), 424242], points=points, sweeps=sweeps)
        idx = np.zeros(0, int)
        if self.outliers > 0:
            rng = np.random.default_rng([int(s), 515151])
            k = int(round(self.outliers * len(d)))
            idx = np.sort(rng.choice(len(d), size=k, replace=False))
            v = rng.normal(size=(k, 3))
            v /= np.linalg.norm(v, axis=1, keepdims=True)
            d.tip = d.tip.copy()
            d.tip[idx] += v * rng.uniform(3.0, 15.0, (k, 1))
            if d.points is not None:
                d.points = d.points.copy()
                d.points[idx, -1] = d.tip[idx]
        d.info["outliers"] = idx.tolist()
        d.info["scenario"] = f"real_robot(seed={self.seed})"
        return d

    def backbones(self, q, points: int = 20, direction=None, path: bool = False,
                  frame: str = "base") -> np.ndarray:
        if frame not in ("base", "sensor"):
            raise ValueError(f"frame must be 'base' or 'sensor', got {frame!r}")
        q = np.atleast_2d(np.asarray(q, float))
        eff = self.mechanics_effects
        if path:
            sweep = np.array(["path"] * len(q))
            _, pts, ok = truth(self.spec, q, eff, direction=directions(q, sweep), sweep=sweep,
                               points=max(int(points), 2))
        else:
            d = None if direction is None else np.asarray(direction)
            _, pts, ok = truth(self.spec, q, eff, direction=d, sweep=None,
                               points=max(int(points), 2))
        if frame == "sensor":
            pts = E.sensor(pts, self.effects, None, q, self.spec)
        if not ok.all():
            pts[~ok] = np.nan
        return pts

    def nominal(self, q, points: int = 20) -> np.ndarray:
        _, pts, _ = truth(self.spec, np.atleast_2d(np.asarray(q, float)), {},
                          points=max(int(points), 2))
        return pts


def real_robot(seed: int = 0, robot="seed1", noise_mm: float = 0.08, registration: bool = False,
               outliers: float = 0.0) -> RealRobot:
    """A realistic truth robot (module docstring); the seed draws the effect magnitudes."""
    spec = load_spec(robot)
    n = spec.n
    rng = np.random.default_rng([int(seed), 777])

    def outer_last(inner, mid, outer):
        return E._outer_last(n, inner, mid, outer)

    pc_scale = [1.0] * n
    if n >= 3:
        pc_scale[1] = 1.0 - 0.10 * (1.0 + rng.uniform(-0.2, 0.2))     # middle tube ~10 % less
    else:
        pc_scale[-1] = 1.0 - 0.10 * (1.0 + rng.uniform(-0.2, 0.2))
    eff = {
        "precurvature": {"scale": pc_scale, "ramp": _jitter(rng, outer_last(0.25, -0.3, 0.25)),
                         "relax": 0.0, "twist": 0.0},
        "stiffness": {"scale": outer_last(1.0, 1.0, 1.0 + 0.25 * (1.0 + rng.uniform(-0.2, 0.2))),
                      "curved": _jitter(rng, outer_last(1.0, 1.0, 1.08), 0.03),
                      "torsion": outer_last(1.0, 1.0, 1.0), "soften": 0.0},
        "clearance": {"amplitude": float(_jitter(rng, 0.02)), "phase_deg": float(rng.uniform(160, 250)),
                      "harmonics": [0.5, 0.32, 0.18], "lean": float(_jitter(rng, 0.004)),
                      "jump": "gap", "snap": 0.0},
        # base lags with the contact growth (1 + h): typical lags ~0.065 / 0.013 / 0.008 rad
        "friction": {"form": "presliding", "lag": _jitter(rng, outer_last(0.044, 0.012, 0.008)),
                     "angle": float(_jitter(rng, 0.2)), "growth": 1.0, "moment": 0.0},
        "torsion": {"gj_scale": 1.0, "coupling": _jitter(rng, outer_last(40.0, 25.0, 20.0)),
                    "play": 0.0},
    }
    if registration:
        eff["registration"] = {"rotvec": _jitter(rng, [0.02, -0.015, 0.025]),
                               "translation": _jitter(rng, [3.0, -2.0, 4.0]),
                               "scale": _jitter(rng, [0.005, -0.004, 0.006]), "mount": 0.0,
                               "sensor": 0.0}
    eff = E.resolve(eff, n, spec)
    return RealRobot(spec=spec, effects=eff, noise_mm=float(noise_mm), outliers=float(outliers),
                     seed=int(seed))
