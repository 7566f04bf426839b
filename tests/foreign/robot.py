"""Robot description for the foreign generator, parsed from the robot YAML with plain
``yaml.safe_load`` (no ctrplan import: this package must share no code with ctrplan).

Units as in DESIGN.md: lengths mm, curvature 1/mm, Young's modulus MPa (N/mm^2), density kg/m^3.
Tube 0 (array index) is the innermost.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

_ROBOT_DIR = Path(__file__).resolve().parents[2] / "ctrplan" / "data" / "robots"
#: robots ctrplan does not ship (other tube counts, lengths, materials): found by name as well
FOREIGN_ROBOT_DIR = Path(__file__).resolve().parent / "robots"
NITINOL_DENSITY = 6450.0  # kg/m^3


@dataclass(frozen=True)
class Spec:
    """Per-tube arrays (n,) and derived stiffnesses (N mm^2)."""

    name: str
    od: np.ndarray
    id: np.ndarray
    straight: np.ndarray
    curved: np.ndarray
    kappa: np.ndarray
    E: np.ndarray
    nu: np.ndarray
    density: np.ndarray            # kg/m^3
    beta_lo: np.ndarray            # per-tube lower bound on beta (mm)

    @property
    def n(self) -> int:
        return len(self.od)

    @property
    def L(self) -> np.ndarray:
        return self.straight + self.curved

    @property
    def I(self) -> np.ndarray:  # noqa: E743 - second moment of area, mm^4
        return np.pi / 64.0 * (self.od ** 4 - self.id ** 4)

    @property
    def area(self) -> np.ndarray:  # mm^2
        return np.pi / 4.0 * (self.od ** 2 - self.id ** 2)

    @property
    def EI(self) -> np.ndarray:
        return self.E * self.I

    @property
    def GJ(self) -> np.ndarray:
        G = self.E / (2.0 * (1.0 + self.nu))
        return G * 2.0 * self.I

    @property
    def weight_per_mm(self) -> np.ndarray:
        """Weight per unit length under 1 g (9.81 m/s^2), N/mm: rho [kg/m^3] * 1e-9 [m^3/mm^3]
        * A [mm^2] * 9.81."""
        return self.density * 1e-9 * self.area * 9.81

    def scaled(self, kappa_scale=None, E_scale=None) -> Spec:
        k = self.kappa if kappa_scale is None else self.kappa * np.asarray(kappa_scale, float)
        E = self.E if E_scale is None else self.E * np.asarray(E_scale, float)
        return replace(self, kappa=k, E=E)


def robot_path(name: str) -> Path:
    """The YAML file of a robot name: a shipped robot (``ctrplan/data/robots``), a foreign one
    (``tests/foreign/robots``), or ``name`` itself as a path."""
    if "/" not in name and not name.endswith(".yaml"):
        for d in (_ROBOT_DIR, FOREIGN_ROBOT_DIR):
            if (d / f"{name}.yaml").exists():
                return d / f"{name}.yaml"
    return Path(name)


def load_spec(robot) -> Spec:
    """``robot``: a Spec, a robot name (shipped: ``seed1``, ``two_tube_nylon``; foreign:
    ``tests/foreign/robots/<name>.yaml``), a YAML path or a dict."""
    if isinstance(robot, Spec):
        return robot
    if isinstance(robot, dict):
        data = robot
    else:
        s = str(robot)
        path = robot_path(s)
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    tubes = data["tubes"]
    def col(key, default=None):
        out = []
        for t in tubes:
            v = t.get(key, default)
            if v is None:
                raise ValueError(f"robot tube lacks {key!r}")
            out.append(float(v))
        return np.array(out)
    straight = col("straight_length")
    lo = -straight
    if data.get("beta_min") is not None:
        lo = np.maximum(lo, np.array(data["beta_min"], float))
    return Spec(
        name=str(data.get("name", "robot")), od=col("od"), id=col("id"), straight=straight,
        curved=col("curved_length"), kappa=col("curvature"), E=col("youngs_modulus"),
        nu=col("poisson_ratio"), density=col("density", NITINOL_DENSITY), beta_lo=lo,
    )


def valid(spec: Spec, q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """DESIGN.md joint constraints, per row."""
    q = np.atleast_2d(q)
    n = spec.n
    b = q[:, n:]
    end = b + spec.L
    ok = np.all(b <= tol, axis=1)
    ok &= np.all(np.diff(b, axis=1) >= -tol, axis=1)            # beta_1 <= ... <= beta_n
    ok &= np.all(np.diff(end, axis=1) <= tol, axis=1)           # inner reach at least as far
    ok &= end[:, -1] >= -tol
    ok &= np.all(b + spec.straight >= -tol, axis=1)             # curved part in front of plane
    ok &= np.all(b >= spec.beta_lo - tol, axis=1)
    ok &= np.all(np.isfinite(q), axis=1)
    return ok


def beta_from_unit(spec: Spec, u: np.ndarray) -> np.ndarray:
    """Map u in [0, 1]^n (B, n) continuously onto valid betas: outermost tube first, each
    inner tube within the interval the constraints leave it."""
    u = np.atleast_2d(u)
    n = spec.n
    L = spec.L
    b = np.zeros_like(u, dtype=float)
    lo_n = max(spec.beta_lo[-1], -L[-1])
    b[:, -1] = lo_n + u[:, -1] * (0.0 - lo_n)
    for i in range(n - 2, -1, -1):
        hi = b[:, i + 1]
        lo = np.maximum(spec.beta_lo[i], b[:, i + 1] + L[i + 1] - L[i])
        lo = np.minimum(lo, hi)
        b[:, i] = lo + u[:, i] * (hi - lo)
    return b
