"""Tubes, robots, joint constraints, YAML I/O and configuration sampling.

Conventions (docs/conventions.md): lengths mm, angles rad, curvature 1/mm, Young's modulus MPa.
Tube index 0 (tube "1" in files) is the innermost. A configuration is
``q = [alpha_1..alpha_n, beta_1..beta_n]``, batch first ``(B, 2n)``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ctrplan.actuators import (
    ACTUATOR_RANGES,
    DEFAULT_ACTUATOR,
    Actuator,
    actuators_from_yaml,
    actuators_to_yaml,
)
from ctrplan.errors import InputError
from ctrplan.io import load_yaml, write_csv_atomic

#: Slack (mm) allowed on the joint constraints, for round-off in files and interpolation.
CONSTRAINT_TOL_MM = 1e-9

SHIPPED_ROBOTS = ("seed1", "two_tube_nylon", "two_tube_wide")

#: Largest bending strain (od/2 x curvature) a curved section may carry when straightened. The
#: most elastic tube materials used for these robots (superelastic nitinol, ~8 % recoverable;
#: polymers) stay below it; above it the tube would not keep its shape, and the mechanics
#: (linear elasticity, small strain) do not apply.
MAX_BENDING_STRAIN = 0.10


@dataclass(frozen=True)
class Tube:
    """One pre-curved elastic tube.

    Lengths in mm, ``curvature`` in 1/mm (the precurvature of the curved distal section, which
    bends the tube toward +x of its own frame), ``youngs_modulus`` in MPa (N/mm^2).
    ``density`` (kg/m^3, optional) is used only by gravity loads; None means "not given"
    (gravity then uses nitinol's :data:`DEFAULT_DENSITY`).
    """

    od: float
    id: float
    straight_length: float
    curved_length: float
    curvature: float
    youngs_modulus: float
    poisson_ratio: float
    density: float | None = None

    @property
    def length(self) -> float:
        """Total length ``L = straight + curved`` (mm)."""
        return self.straight_length + self.curved_length

    @property
    def second_moment(self) -> float:
        """Area second moment of the annulus, mm^4."""
        return math.pi / 64.0 * (self.od**4 - self.id**4)

    @property
    def area(self) -> float:
        """Cross-section area of the annulus, mm^2."""
        return math.pi / 4.0 * (self.od**2 - self.id**2)

    @property
    def weight_density(self) -> float:
        """Mass per unit length, kg/mm (``density``, or nitinol's when not given)."""
        rho = DEFAULT_DENSITY if self.density is None else self.density
        return rho * self.area * 1e-9

    @property
    def bending_stiffness(self) -> float:
        """EI in N mm^2."""
        return self.youngs_modulus * self.second_moment

    @property
    def torsional_stiffness(self) -> float:
        """GJ in N mm^2 with G = E / (2 (1 + nu)) and J = 2 I."""
        shear = self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))
        return shear * 2.0 * self.second_moment


#: Plausibility ranges (inclusive) of every number in a robot, a model file or a configuration,
#: in the units of docs/conventions.md ("Plausibility ranges" lists the same table). A value
#: outside is refused as a typo or a units mistake before any mechanics runs: finite but absurd
#: values (an angle of 1e20 rad, a translation of 1e12 mm, E = 1e300 MPa) would otherwise give
#: overflowing, NaN or meaningless shapes.
PLAUSIBLE: dict[str, tuple[float, float]] = {
    "diameter": (0.0, 50.0),            # od, id (mm): the widest catheter-like tube is ~10 mm
    "length": (0.0, 5000.0),            # straight/curved length, |beta| (mm)
    "curvature": (-10.0, 10.0),         # 1/mm (a bend radius of at least 0.1 mm)
    "youngs_modulus": (1.0, 2.0e6),     # MPa: soft silicone ~1, nitinol 6e4, tungsten 4e5
    "shear_modulus": (0.3, 1.0e6),      # MPa, G = E / (2 (1 + nu)) (follows from the two)
    "poisson_ratio": (0.0, 0.5),        # dimensionless, 0.5 itself excluded (incompressible)
    "density": (100.0, 25000.0),        # kg/m^3: foams to tungsten/osmium
    "angle": (-1.0e4, 1.0e4),           # rad: unwrapped tube rotations (~1600 turns)
    **ACTUATOR_RANGES,                  # actuator speed and acceleration limits (actuators.py)
}


def check_plausible(value: float, kind: str, source: str, field_: str, unit: str = "") -> float:
    """``value`` as a float when finite and inside :data:`PLAUSIBLE` [kind]; else InputError
    naming ``source`` and ``field_`` (one line, with the range and unit)."""
    lo, hi = PLAUSIBLE[kind]
    v = float(value)
    if not math.isfinite(v):
        raise InputError(source, field_, f"must be a finite number, got {v!r}")
    if not lo <= v <= hi:
        raise InputError(source, field_, f"{v:.6g} is outside the plausible range [{lo:g}, {hi:g}]"
                                         f"{' ' + unit if unit else ''} (a typo or a units mistake?)")
    return v


#: Required tube fields (``density`` is optional).
_TUBE_FIELDS = tuple(f.name for f in fields(Tube) if f.name != "density")

#: Density (kg/m^3) used for gravity loads of a tube without ``density``: nitinol.
DEFAULT_DENSITY = 6450.0


@dataclass(frozen=True)
class Robot:
    """A set of concentric tubes, innermost first, with joint limits.

    ``beta_min`` optionally narrows each tube's translation range (mm, <= 0); by default a tube
    may be retracted until its curved section starts at the constraint plane. ``actuators``
    optionally gives each tube's speed and acceleration limits (:class:`~ctrplan.actuators.
    Actuator`, one per tube, innermost first); None means the defaults for every tube (a tuple
    of defaults is stored as None, so equal limits make equal robots).
    """

    name: str
    tubes: tuple[Tube, ...]
    beta_min: tuple[float, ...] | None = None
    source: str = field(default="<memory>", compare=False)
    actuators: tuple[Actuator, ...] | None = None

    def __post_init__(self) -> None:
        _validate_tubes(self.tubes, self.source)
        if self.beta_min is not None and len(self.beta_min) != len(self.tubes):
            raise InputError(self.source, "beta_min", f"needs {len(self.tubes)} values, one per tube")
        if self.actuators is not None:
            acts = tuple(self.actuators)
            if len(acts) != len(self.tubes) or not all(isinstance(a, Actuator) for a in acts):
                raise InputError(self.source, "actuators", f"needs {len(self.tubes)} actuators, "
                                                           "one per tube")
            object.__setattr__(self, "actuators",
                               None if all(a == DEFAULT_ACTUATOR for a in acts) else acts)

    # ------------------------------------------------------------------ basic properties
    @property
    def n(self) -> int:
        """Number of tubes."""
        return len(self.tubes)

    @property
    def dof(self) -> int:
        """Length of a configuration vector, ``2 n``."""
        return 2 * self.n

    def array(self, name: str) -> np.ndarray:
        """Per-tube property as an ``(n,)`` array (any Tube attribute or property); a fresh
        copy of the values read once (the robot is immutable; shape models ask per call)."""
        cache = self.__dict__.setdefault("_arrays", {})
        hit = cache.get(name)
        if hit is None:
            hit = cache[name] = np.array([getattr(t, name) for t in self.tubes], dtype=float)
        return hit.copy()

    @property
    def lengths(self) -> np.ndarray:
        return self.array("length")

    @property
    def column_names(self) -> list[str]:
        """Configuration column names ``alpha1..alphaN, beta1..betaN`` (files are 1-based)."""
        return [f"alpha{i + 1}" for i in range(self.n)] + [f"beta{i + 1}" for i in range(self.n)]

    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-joint ``(max_speed, max_accel)``, each ``(2n,)`` in the order of ``q``: the
        rotations (rad/s, rad/s^2) then the translations (mm/s, mm/s^2)."""
        acts = self.actuators or (DEFAULT_ACTUATOR,) * self.n
        joints = [a.rotation for a in acts] + [a.translation for a in acts]
        return (np.array([j.max_speed for j in joints], dtype=float),
                np.array([j.max_accel for j in joints], dtype=float))

    def beta_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-tube box bounds ``(lo, hi)`` on beta implied by the constraints (mm)."""
        lo = -self.array("straight_length")
        if self.beta_min is not None:
            lo = np.maximum(lo, np.asarray(self.beta_min, dtype=float))
        hi = np.zeros(self.n)
        return lo, hi

    def retracted(self) -> np.ndarray:
        """A valid 'retracted' start configuration ``(2n,)``: all alpha 0, every tube pulled
        back as far as the constraints allow.

        The joint constraints on beta are all of the form ``beta_j - beta_i <= c`` or bounds
        (a system of difference constraints), so the valid betas, when there are any, have a
        least element: each beta at its smallest valid value at once. It is found by raising
        every beta from its lower bound to what the constraints demand, until nothing changes
        (at most n + 1 rounds, as in Bellman-Ford); if that exceeds an upper bound, no valid
        configuration exists. (Retracting the outermost tube first and fitting the inner ones
        to it, as before, can end outside the constraints, e.g. when an outer tube's straight
        section is longer than an inner tube's.)
        """
        lo, hi = self.beta_bounds()
        L = self.lengths
        n = self.n
        beta = lo.copy()
        beta[-1] = max(beta[-1], -L[-1])                      # the outermost tube leaves the plane
        for _ in range(n + 1):
            before = beta.copy()
            for i in range(n - 1):
                beta[i + 1] = max(beta[i + 1], beta[i])                       # beta_i <= beta_i+1
                beta[i] = max(beta[i], beta[i + 1] + L[i + 1] - L[i])         # inner reaches further
            if np.array_equal(beta, before):
                break
        q = np.concatenate([np.zeros(n), beta])
        if np.any(beta > hi + CONSTRAINT_TOL_MM) or not self.is_valid(q[None])[0]:
            raise InputError(self.source, "tubes", "the joint constraints admit no configuration")
        return q

    # ------------------------------------------------------------------ constraints
    def constraint_violations(self, q: np.ndarray) -> np.ndarray:
        """Signed constraint values ``(B, C)``; a configuration is valid when all are >= 0.

        q : (B, 2n) float, rad and mm.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n = self.n
        beta = q[:, n:]
        L = self.lengths
        lo, hi = self.beta_bounds()
        cols = [hi - beta, beta - lo]                      # beta_i <= 0, beta_i >= lower
        if n > 1:
            cols.append(beta[:, 1:] - beta[:, :-1])         # beta_i <= beta_(i+1)
            cols.append((beta[:, :-1] + L[:-1]) - (beta[:, 1:] + L[1:]))  # inner reaches further
        cols.append(beta[:, -1:] + L[-1])                   # outermost tube leaves the plane
        return np.concatenate(cols, axis=1)

    def check_plausible(self, q: np.ndarray, source: str, row_offset: int = 2) -> None:
        """Refuse rotations or translations outside :data:`PLAUSIBLE` (InputError naming the
        row and column); see :func:`check_config_plausible`."""
        check_config_plausible(q, self, source, row_offset=row_offset)

    def is_valid(self, q: np.ndarray) -> np.ndarray:
        """``(B,)`` bool: finite and inside the joint constraints. q : (B, 2n)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if q.shape[1] != self.dof:
            raise ValueError(f"q has {q.shape[1]} columns, robot {self.name!r} needs {self.dof}")
        finite = np.all(np.isfinite(q), axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.all(self.constraint_violations(q) >= -CONSTRAINT_TOL_MM, axis=1)
        return finite & ok

    def sample(self, n: int, seed: int | np.random.Generator | None = 0) -> np.ndarray:
        """``(n, 2n_tubes)`` configurations uniform over the valid set.

        Alphas are uniform on (-pi, pi]; betas are uniform over the constraint polytope
        (rejection sampling from its bounding box, which is exact).
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise InputError("n", "", f"the number of samples must be an integer >= 0, got {n!r}")
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed < 0:
            raise InputError("seed", "", f"must be >= 0, got {seed}")
        if n == 0:
            return np.empty((0, self.dof))
        rng = np.random.default_rng(seed)
        lo, hi = self.beta_bounds()
        out: list[np.ndarray] = []
        have = 0
        drawn = 0
        while have < n:
            if drawn >= max(1_000_000, 1000 * n):
                # e.g. two tubes of equal length force beta_i = beta_(i+1): a set of zero volume;
                # a budget of draws, so a sliver of valid volume cannot run for ever either
                raise InputError(self.source, "tubes", "the joint constraints leave (almost) no "
                                 f"volume to sample from: {have} valid configurations in "
                                 f"{drawn} draws")
            m = max(4096, 2 * (n - have))
            drawn += m
            beta = rng.uniform(lo, hi, size=(m, self.n))
            alpha = -rng.uniform(-math.pi, math.pi, size=(m, self.n))  # maps [-pi, pi) -> (-pi, pi]
            q = np.concatenate([alpha, beta], axis=1)
            q = q[self.is_valid(q)]
            out.append(q)
            have += len(q)
        return np.concatenate(out, axis=0)[:n]

    def tip_length(self, q: np.ndarray) -> np.ndarray:
        """Backbone arc length from the constraint plane to the tip, ``(B,)`` mm."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return np.max(q[:, self.n:] + self.lengths, axis=1)

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "name": self.name,
            "tubes": [{k: float(getattr(t, k)) for k in _TUBE_FIELDS}
                      | ({} if t.density is None else {"density": float(t.density)})
                      for t in self.tubes],
        }
        if self.beta_min is not None:
            d["beta_min"] = [float(b) for b in self.beta_min]
        if self.actuators is not None:     # written only when not the defaults (stable digests)
            d["actuators"] = actuators_to_yaml(self.actuators)
        return d

    def save(self, path: str | os.PathLike) -> None:
        """Write the robot YAML (units noted in a header comment)."""
        import yaml

        from ctrplan.io import write_text_atomic

        text = (
            "# ctrplan robot: lengths mm, curvature 1/mm, youngs_modulus MPa, density kg/m^3; "
            "actuators rad/s, rad/s^2 (rotation), mm/s, mm/s^2 (translation); "
            "tubes innermost first\n"
            + yaml.safe_dump(self.to_dict(), sort_keys=False)
        )
        write_text_atomic(path, text)


def robot_digest(spec: dict[str, Any]) -> str:
    """sha256 (hex) of a robot's values (:meth:`Robot.to_dict`: tubes, and the actuator limits
    where they are not the defaults) in canonical JSON: the
    ``robot_sha256`` field of plan.json (equal digests = the same robot, whatever its name or
    file)."""
    import hashlib
    import json

    text = json.dumps(spec, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def robot_record(robot: Robot) -> dict[str, Any]:
    """The plan.json fields that carry the robot itself: ``robot_spec`` (its tube values, as in
    a robot YAML) and ``robot_sha256`` (:func:`robot_digest` of them)."""
    spec = robot.to_dict()
    return {"robot_spec": spec, "robot_sha256": robot_digest(spec)}


def robot_from_record(plan: dict[str, Any], source: str) -> Robot | None:
    """The robot a plan.json was planned with, from its ``robot_spec`` (validated as a robot
    file, and against ``robot_sha256`` when present); None when the plan has no robot_spec (a
    plan written before it was recorded)."""
    spec = plan.get("robot_spec")
    if spec is None:
        return None
    robot = robot_from_dict(spec, source=f"{source}: robot_spec")
    digest = plan.get("robot_sha256")
    if digest is not None:
        try:
            same = isinstance(digest, str) and robot_digest(spec) == digest
        except (TypeError, ValueError):
            same = False
        if not same:
            raise InputError(source, "robot_sha256", "does not match robot_spec: the plan was "
                             "edited after planning, so the robot that planned is unknown")
    return robot


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    return math.pi - np.mod(math.pi - a, 2.0 * math.pi)


def _validate_tubes(tubes: tuple[Tube, ...], source: str) -> None:
    if len(tubes) == 0:
        raise InputError(source, "tubes", "a robot needs at least one tube")
    for i, t in enumerate(tubes):
        where = f"tubes[{i}]"
        for k in _TUBE_FIELDS:
            v = getattr(t, k)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise InputError(source, f"{where}.{k}", f"must be a finite number, got {v!r}")
        for k, kind, unit in (("od", "diameter", "mm"), ("id", "diameter", "mm"),
                              ("straight_length", "length", "mm"),
                              ("curved_length", "length", "mm"),
                              ("curvature", "curvature", "1/mm"),
                              ("youngs_modulus", "youngs_modulus", "MPa")):
            check_plausible(getattr(t, k), kind, source, f"{where}.{k}", unit)
        if t.od <= 0:
            raise InputError(source, f"{where}.od", f"must be > 0, got {t.od}")
        if not 0 <= t.id < t.od:
            raise InputError(source, f"{where}.id", f"must satisfy 0 <= id < od ({t.od}), got {t.id}")
        if t.straight_length < 0:
            raise InputError(source, f"{where}.straight_length", f"must be >= 0, got {t.straight_length}")
        if t.curved_length < 0:
            raise InputError(source, f"{where}.curved_length", f"must be >= 0, got {t.curved_length}")
        if t.length <= 0:
            raise InputError(source, f"{where}", "straight_length + curved_length must be > 0")
        strain = 0.5 * t.od * abs(t.curvature)
        if strain > MAX_BENDING_STRAIN:
            raise InputError(
                source, f"{where}.curvature",
                f"tube {i + 1} (od {t.od:g} mm) with curvature {t.curvature:g} 1/mm would be "
                f"strained {100 * strain:.3g} % when straightened (od/2 x curvature), beyond the "
                f"{100 * MAX_BENDING_STRAIN:g} % any elastic tube material survives: is the "
                f"curvature in 1/mm (not 1/m or a radius)?")
        if t.youngs_modulus <= 0:
            raise InputError(source, f"{where}.youngs_modulus", f"must be > 0, got {t.youngs_modulus}")
        if not 0 <= t.poisson_ratio < 0.5:
            raise InputError(source, f"{where}.poisson_ratio", f"must be in [0, 0.5), got {t.poisson_ratio}")
        check_plausible(t.torsional_stiffness / (2.0 * t.second_moment), "shear_modulus", source,
                        f"{where}.youngs_modulus", "MPa (shear modulus E / (2 (1 + nu)))")
        if t.density is not None and (isinstance(t.density, bool)
                                      or not isinstance(t.density, (int, float))
                                      or not math.isfinite(t.density) or t.density <= 0):
            raise InputError(source, f"{where}.density",
                             f"must be a finite number > 0 (kg/m^3), got {t.density!r}")
        if t.density is not None:
            check_plausible(t.density, "density", source, f"{where}.density", "kg/m^3")
        if i > 0 and not tubes[i - 1].od < t.id:
            raise InputError(
                source, f"{where}.id",
                f"must exceed the OD of the tube inside it ({tubes[i - 1].od} mm), got {t.id}",
            )


def robot_from_dict(data: Any, source: str = "<memory>") -> Robot:
    """Build a :class:`Robot` from parsed YAML; unknown keys are errors."""
    if not isinstance(data, dict):
        raise InputError(source, "", "expected a mapping with 'name' and 'tubes'")
    unknown = set(data) - {"name", "tubes", "beta_min", "actuators", "units", "notes", "source"}
    if unknown:
        raise InputError(source, sorted(unknown, key=str)[0], "unknown key")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise InputError(source, "name", "must be a non-empty string")
    raw = data.get("tubes")
    if not isinstance(raw, list) or not raw:
        raise InputError(source, "tubes", "must be a non-empty list of tubes (innermost first)")
    tubes = []
    for i, t in enumerate(raw):
        if not isinstance(t, dict):
            raise InputError(source, f"tubes[{i}]", "must be a mapping")
        unknown = set(t) - set(_TUBE_FIELDS) - {"density"}
        if unknown:
            raise InputError(source, f"tubes[{i}].{sorted(unknown, key=str)[0]}", "unknown key")
        missing = [k for k in _TUBE_FIELDS if k not in t]
        if missing:
            raise InputError(source, f"tubes[{i}].{missing[0]}", "missing")
        vals = {}
        for k in _TUBE_FIELDS:
            v = t[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(source, f"tubes[{i}].{k}", f"must be a number, got {v!r}")
            vals[k] = float(v)
        if "density" in t:
            v = t["density"]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(source, f"tubes[{i}].density",
                                 f"must be a number (kg/m^3), got {v!r}")
            vals["density"] = float(v)
        tubes.append(Tube(**vals))
    beta_min = data.get("beta_min")
    if beta_min is not None:
        if not isinstance(beta_min, list) or not all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in beta_min
        ):
            raise InputError(source, "beta_min", "must be a list of finite numbers (mm)")
        if any(b > 0 for b in beta_min):
            raise InputError(source, "beta_min", "values must be <= 0 mm")
        for i, b in enumerate(beta_min):
            check_plausible(-b, "length", source, f"beta_min[{i}]", "mm (as a retraction)")
        beta_min = tuple(float(b) for b in beta_min)
    actuators = (actuators_from_yaml(data["actuators"], len(tubes), source)
                 if "actuators" in data else None)
    return Robot(name=name, tubes=tuple(tubes), beta_min=beta_min, source=source,
                 actuators=actuators)


def load_robot(name_or_path: str | os.PathLike | Robot) -> Robot:
    """Load a shipped robot by name (``seed1``, ``two_tube_nylon``) or a robot YAML file."""
    if isinstance(name_or_path, Robot):
        return name_or_path
    s = str(name_or_path)
    if s in SHIPPED_ROBOTS:
        ref = resources.files("ctrplan") / "data" / "robots" / f"{s}.yaml"
        with resources.as_file(ref) as p:
            data = load_yaml(p)
            return robot_from_dict(data, source=s)
    path = Path(s)
    if not path.exists():
        raise InputError(s, "", f"no such robot file, and not a shipped robot ({', '.join(SHIPPED_ROBOTS)})")
    check_regular_file(path, (".yaml", ".yml"), "a robot YAML")
    return robot_from_dict(load_yaml(path), source=str(path))


#: Largest robot or calibrated-model YAML read (bytes): real ones are about 1 kB.
MAX_YAML_BYTES = 1 << 20


def check_regular_file(path: str | os.PathLike, suffixes: tuple[str, ...], what: str,
                       max_bytes: int = MAX_YAML_BYTES) -> Path:
    """``path`` when it is a regular file (after symlinks) with one of ``suffixes`` and at most
    ``max_bytes`` long; else InputError. Keeps devices (/dev/zero), FIFOs, folders and
    arbitrary files named as a robot or model out of the readers."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        raise InputError(str(path), "", "file not found") from None
    import stat as _stat

    if not _stat.S_ISREG(st.st_mode):
        raise InputError(str(path), "", f"not a regular file: expected {what}")
    if not p.name.lower().endswith(suffixes):
        raise InputError(str(path), "", f"expected {what} ({' or '.join(suffixes)} file)")
    if st.st_size > max_bytes:
        raise InputError(str(path), "", f"{st.st_size} bytes is more than {what} can be "
                                        f"({max_bytes} bytes)")
    return p


def read_configs(path: str | os.PathLike, robot: Robot, check: bool = True) -> np.ndarray:
    """Read a configuration CSV (header ``alpha1..alphaN,beta1..betaN``) as ``(B, 2n)``.

    Extra columns are allowed (measured data carries tip columns), but not tube columns the
    robot does not have. With ``check`` every row must satisfy the joint constraints. Parsed
    in chunks (:func:`ctrplan.io.iter_configs`); commands over many rows stream instead.
    """
    from ctrplan.io import iter_configs

    return np.concatenate([q for q, _ in iter_configs(path, robot, check, kind="csv")])


def check_config_plausible(q: np.ndarray, robot: Robot, source: str, row_offset: int = 2,
                           row_word: str = "row") -> None:
    """Refuse configurations whose rotations or translations lie outside :data:`PLAUSIBLE`
    (|alpha| <= 1e4 rad, |beta| <= 5000 mm), naming the row (``row_offset`` + index) and the
    column. Finite values beyond these lose all precision (1e20 rad has no meaningful angle)."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if q.size == 0:
        return
    n = robot.n
    for cols, kind, unit in ((slice(0, n), "angle", "rad"), (slice(n, 2 * n), "length", "mm")):
        lo, hi = PLAUSIBLE[kind]
        lo = -hi if kind == "length" else lo
        block = q[:, cols]
        bad = ~((block >= lo) & (block <= hi))
        if bad.any():
            k, j = (int(x[0]) for x in np.nonzero(bad))
            name = robot.column_names[cols.start + j]
            raise InputError(source, f"{row_word} {k + row_offset}: {name}",
                             f"{block[k, j]:.6g} is outside the plausible range [{lo:g}, {hi:g}] "
                             f"{unit} (a typo or a units mistake?)")


def write_configs(path: str | os.PathLike, robot: Robot, q: np.ndarray) -> None:
    """Write configurations ``(B, 2n)`` as CSV with the standard header."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    write_csv_atomic(path, robot.column_names, q.tolist())
