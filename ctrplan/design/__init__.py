"""``ctrplan design``: a tube set designed for an anatomy and its targets.

:func:`design` searches curvature, curved length, straight length and stock size of each tube
(:mod:`ctrplan.design.space`) for the design that reaches the most targets by a verified
collision-free plan from the scene's entry (a :class:`ctrplan.planning.Planner` per design, physics
model, the planning model's margin), then has the most clearance along those plans, then is
the simplest (fewer, less curved, shorter tubes). Hard constraints (named in the results when
they bind): nitinol's recoverable strain, nesting with a radial gap, length and stroke limits,
elastic stability along every planned path, and a collision-free start at the scene's entry.

Parallel evaluation (:class:`DesignConfig` ``workers`` or ``ray_address``): a local process
pool, or Ray through :mod:`ctrplan.planning.ray_pool` (the code path of ``plan-batch --ray``),
started while the anatomy is read (:mod:`ctrplan.design.runner`). Candidates of a generation
are fixed before they are evaluated; plans run beside the following generations' screens and
are taken into account a fixed number of generations after they were chosen
(:data:`ctrplan.design.search.PLAN_LAG`), so the design does not depend on where, when or in
which order evaluations ran.

Layering: design uses robot, shape, collision and planning; nothing imports design.
``ctrplan.design`` is also callable: ``ctrplan.design(scene, targets, ...)`` is
:func:`design`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
import types
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from ctrplan.design.space import (
    DEFAULT_STRAIN_LIMIT,
    Bounds,
    constraint_report,
    load_stock,
    make_space,
)
from ctrplan.errors import InputError
from ctrplan.robot import Robot

log = logging.getLogger("ctrplan")

__all__ = ["DEFAULT_STRAIN_LIMIT", "Bounds", "DesignConfig", "DesignResult", "DesignStatus", "TargetOutcome", "design", "resolve_scene",
           "resolve_targets"]


class DesignStatus(str, Enum):
    """Outcome of :func:`design`."""

    ALL_REACHED = "ALL_REACHED"      # the design reaches every target
    PARTIAL = "PARTIAL"              # some targets reached
    NONE_REACHED = "NONE_REACHED"    # no design evaluated reaches any target


@dataclass(frozen=True)
class DesignConfig:
    """Settings of :func:`design` (defaults: what ``ctrplan design`` uses).

    tubes : the largest number of tubes (1-3; designs with fewer are tried and preferred).
    seed : seeds the search and every plan (same seed, same design).
    budget : designs screened (a count, in whole generations: the last may go past it);
        plan_budget : designs planned in full (None:
        max(4, min(24, budget // 6))).
    time_limit : wall-clock cap (s); ``time_cap_hit`` when it stopped the search.
    workers : local worker processes (results do not depend on it; plans of one generation
        run beside the screens of the next ones, :mod:`ctrplan.design.search`).
    ray_address : run the evaluations on Ray instead (the same path as ``plan-batch --ray``,
        :mod:`ctrplan.planning.ray_pool`): a cluster address, or ``"local"`` to start a Ray
        instance on this machine with every core; results do not depend on it either.
        Excludes ``workers > 1``. Needs ``pip install 'ctrplan[ray]'``.
    generation : designs per generation (fixed, so results do not depend on ``workers``):
        the CMA-ES populations of every tube count together (at least 4 each), screened in
        parallel.
    plans_per_generation : designs planned in full per generation at most (their targets are
        planned in parallel).
    derive : search the ranges read from the anatomy (:mod:`ctrplan.design.derive`) inside
        ``bounds``; False searches ``bounds`` as they are.
    patience : once every target is reached, the search stops after this many generations
        without more clearance (up to ``clearance_goal_mm``; the estimate along the plans);
        simpler designs of the same reach and clearance do not hold it.
    bounds : design-variable bounds and constraint limits (:class:`~ctrplan.design.space.Bounds`;
        ``strain_limit`` default 6 %, see :data:`~ctrplan.design.space.DEFAULT_STRAIN_LIMIT`).
    stock : a CSV of stock tube sizes (od_mm,id_mm), None for the shipped table.
    margin_mm : planning margin (None: the planning model's own bound, 0 for physics).
    tolerance_mm : tip-to-target distance a plan must reach.
    screen_samples : configurations sampled per design in the workspace pre-screen.
    plan_time_s, plan_states : per-plan wall-clock cap and state budget.
    stability_step_mm, stability_step_rad : interpolation of each path for the stability check.
    """

    tubes: int = 2
    seed: int = 0
    budget: int = 400
    plan_budget: int | None = None
    time_limit: float = 1200.0
    workers: int = 1
    ray_address: str | None = None
    generation: int = 16
    plans_per_generation: int = 2
    derive: bool = True
    patience: int = 3
    clearance_goal_mm: float = 0.5
    bounds: Bounds = field(default_factory=Bounds)
    stock: str | None = None
    margin_mm: float | None = None
    tolerance_mm: float = 1.0
    screen_samples: int = 1024
    plan_time_s: float = 10.0
    plan_states: int = 30_000
    stability_step_mm: float = 1.0
    stability_step_rad: float = 0.02

    def __post_init__(self) -> None:
        for name in ("budget", "generation", "screen_samples", "plan_states", "workers",
                     "plans_per_generation"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InputError(f"--{name.replace('_', '-')}", "", f"must be an integer >= 1, got {v!r}")
        if self.plan_budget is not None and (not isinstance(self.plan_budget, int) or self.plan_budget < 1):
            raise InputError("plan_budget", "", f"must be an integer >= 1, got {self.plan_budget!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise InputError("--seed", "", f"must be >= 0, got {self.seed!r}")
        if not (isinstance(self.time_limit, (int, float)) and self.time_limit > 0):
            raise InputError("--time", "", f"must be > 0 s, got {self.time_limit!r}")
        if self.ray_address is not None:
            if not isinstance(self.ray_address, str) or not self.ray_address.strip():
                raise InputError("--ray", "", f"must be a Ray address or 'local', got {self.ray_address!r}")
            if self.workers > 1:
                raise InputError("--workers", "", "use either --workers (a local process pool) or --ray, not both")
        if self.margin_mm is not None and not (math.isfinite(self.margin_mm) and self.margin_mm >= 0):
            raise InputError("--margin", "", f"must be >= 0 mm, got {self.margin_mm!r}")


@dataclass(frozen=True)
class TargetOutcome:
    """One target under the chosen design: ``reached`` by a verified, stable, collision-free
    plan; ``clearance_mm`` (min along the plan, planning and reference model: a lower bound,
    0 where the plan's distance queries did not settle it), ``clearance_estimate_mm`` (FCL's
    minimum where settled, else the distance fields' estimate at the path's states: what
    designs are ranked by, not a bound), ``tip_error_mm``
    (physics), ``status`` (the plan's, or UNSTABLE / NOT_TRIED), ``plan`` (the PlanResult)."""

    name: str
    position: np.ndarray
    reached: bool
    status: str
    clearance_mm: float
    tip_error_mm: float
    plan: object = None
    clearance_estimate_mm: float = math.nan


@dataclass(frozen=True)
class DesignResult:
    """Result of :func:`design`.

    success : every target reached. robot : the chosen design (None when no design was
    feasible). targets : per target outcome. evaluations : every design evaluated (dicts as in
    design.json). binding : hard constraints that bind at the chosen design. constraints :
    each constraint's value, limit, satisfied, binds. timings : seconds per stage.
    anatomy : the anatomy read before the search (:meth:`Anatomy.to_json`); space : the design
    space derived from it (None with ``derive=False``); blocked : per target not reached, what
    blocks it (:func:`ctrplan.design.explain.explain`); closest : the closest design found (the
    best by the search's ranking; with ``robot`` None, the only design there is to show).
    schedule : the jobs' submission and wait log with each job's seconds
    (:meth:`ctrplan.design.runner.Runner.schedule`; the scaling benchmark replays it).
    """

    success: bool
    status: DesignStatus
    message: str
    robot: Robot | None
    targets: tuple[TargetOutcome, ...]
    evaluations: tuple[dict, ...]
    binding: tuple[str, ...]
    constraints: dict
    timings: dict
    counts: dict
    seed: int
    scene: str
    time_cap_hit: bool = False
    config: DesignConfig = field(default_factory=DesignConfig)
    anatomy: dict | None = None
    space: dict | None = None
    blocked: tuple[dict, ...] = ()
    closest: dict | None = None
    schedule: dict | None = None

    @property
    def reached(self) -> int:
        """Number of targets reached."""
        return sum(t.reached for t in self.targets)


def resolve_scene(spec):
    """A scene by name (shipped anatomy, or the design test scene ``design_bend``), folder or
    object; InputError without a wall mesh (design needs the lumen to stay inside)."""
    from ctrplan.collision.scene import anatomy_dir, load_scene

    if isinstance(spec, (str, os.PathLike)):
        s = str(spec)
        packaged = Path(__file__).resolve().parents[1] / "data" / "scenes" / s
        if not Path(s).exists() and not (anatomy_dir() / s).is_dir() and (packaged / "scene.yaml").is_file():
            spec = str(packaged)
    scene = load_scene(spec)
    if not any(m.role == "wall" for m in scene.meshes):
        raise InputError(str(Path(scene.path) / "scene.yaml"), "meshes",
                         "no wall mesh: design needs the lumen the robot stays inside (role: wall)")
    return scene


def resolve_targets(scene, targets) -> tuple[list[str], np.ndarray]:
    """(names, (T, 3) scene-frame positions) from target names of the scene (a list or a
    comma-separated string), a CSV path (columns x,y,z and optionally name), or an array."""
    if isinstance(targets, str) and (targets.lower().endswith(".csv") or Path(targets).is_file()):
        from ctrplan.planning.batch import read_targets

        rows = read_targets(targets, [str(scene.path)])
        return [r[1] for r in rows], np.array([r[2] for r in rows], dtype=float)
    if isinstance(targets, str):
        targets = [t.strip() for t in targets.split(",") if t.strip()]
    if isinstance(targets, np.ndarray) and targets.dtype.kind == "f":
        pts = np.atleast_2d(targets).astype(float)
        if pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
            raise InputError("targets", "", "need (T, 3) finite positions (mm)")
        return [f"p{i + 1}" for i in range(len(pts))], pts
    names = list(targets)
    if not names:
        raise InputError("--targets", "", "no targets given")
    found = [scene.find_target(n) for n in names]   # anatomical names or ids (t01..)
    for n, t in zip(names, found):
        if t is None:
            raise InputError("--targets", "", f"unknown target {n!r} in scene {scene.name!r} "
                             f"(known: {scene.target_names()})")
    return names, np.array([t.position for t in found], dtype=float)


def _state_key(scene, names, pts, cfg: DesignConfig, fixed) -> str:
    d = {"scene": str(scene.path), "targets": [names, np.round(pts, 6).tolist()],
         "cfg": {k: v for k, v in asdict(cfg).items() if k not in ("workers", "ray_address", "time_limit")},
         "fixed": [asdict(t) for t in fixed], "version": 1}
    return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()


def _starts(space, anatomy, scene):
    """The arc fitted to the corridors (:func:`ctrplan.design.seed.fit_arc`) and the search's
    start point per number of designed tubes (the cube's centre without derived ranges)."""
    from ctrplan.design.seed import fit_arc, start_point

    if space.derived is None or not space.k_max:
        return None, {}
    r = space.derived.inner
    fit = fit_arc(anatomy, np.asarray(scene.base_pose, float), space.stock[r.sizes[0]][0] / 2,
                  r.curvature, r.curved_length)
    return fit, {k: start_point(space, k, fit) for k in range(max(1, space.k_min), space.k_max + 1)}


def _ruled_out(anatomy, cfg: DesignConfig, stock, fixed, designed: int) -> bool:
    """Whether a necessary condition (:mod:`ctrplan.design.explain`) fails for every target."""
    from ctrplan.design.explain import explain

    pre = explain(anatomy, cfg.bounds, stock, fixed, designed, cfg.margin_mm or 0.0, cfg.tolerance_mm, [], None)
    return bool(pre) and all(b["kind"] == "necessary" for b in pre)


def read_anatomy(scene, names, pts: np.ndarray, cfg: DesignConfig, stock, curvature_bound: float):
    """The anatomy read (:func:`ctrplan.design.anatomy.analyse`) and the design space derived
    from it (:func:`ctrplan.design.derive.derive`) for ``cfg``'s bounds."""
    from ctrplan.collision.world import world_for
    from ctrplan.design.anatomy import analyse
    from ctrplan.design.derive import derive

    world = world_for(scene, 0.0, curvature_bound)      # only its distance fields are used
    radii = np.array([od / 2 for od, _ in stock])
    anatomy = analyse(scene, world, names, pts, radii, tolerance_mm=cfg.tolerance_mm)
    return anatomy, derive(anatomy, cfg.bounds, stock, margin_mm=cfg.margin_mm or 0.0)


def design(scene, targets, config: DesignConfig | None = None, start_from: Robot | str | None = None,
           out: str | os.PathLike | None = None, progress: bool = True) -> DesignResult:
    """Design a tube set for ``scene`` and ``targets``.

    Parameters
    ----------
    scene : shipped name, folder or Scene (needs a wall mesh).
    targets : names of the scene's targets (list or "a,b"), a CSV path (x,y,z[,name]) or a
        (T, 3) array (mm, scene frame).
    config : DesignConfig.
    start_from : a robot whose tubes are kept as they are (outermost; ``--from``); designed
        tubes go inside them. It must satisfy the strain limit.
    out : folder for the resumable search state (``state.json``); None keeps it in memory.
    progress : show a progress bar (on a terminal).

    Raises
    ------
    InputError
        Unknown scene or target, a scene without a wall, infeasible bounds (named), a
        ``start_from`` robot beyond the strain limit.
    """
    from ctrplan.design.evaluate import EvalSettings
    from ctrplan.design.runner import Runner
    from ctrplan.robot import load_robot

    cfg = config or DesignConfig()
    if cfg.ray_address is not None:
        from ctrplan.planning.ray_pool import require_ray

        require_ray()       # before anything is loaded or written
    t0 = time.perf_counter()
    sc = resolve_scene(scene)
    names, pts = resolve_targets(sc, targets)
    fixed: tuple = ()
    src = ""
    if start_from is not None:
        fr = load_robot(start_from)
        fixed, src = fr.tubes, str(fr.source if fr.source != "<memory>" else "--from")
    stock = load_stock(cfg.stock)
    make_space(cfg.bounds, stock, fixed, cfg.tubes, source=src)      # bad bounds: before any work
    kbound = max([cfg.bounds.curvature[1]] + [abs(t.curvature) for t in fixed])
    settings = EvalSettings(screen_samples=cfg.screen_samples, tolerance_mm=cfg.tolerance_mm,
                            margin_mm=cfg.margin_mm, plan_time_s=cfg.plan_time_s,
                            plan_states=cfg.plan_states, stability_step_mm=cfg.stability_step_mm,
                            stability_step_rad=cfg.stability_step_rad, curvature_bound=float(kbound),
                            screen_tolerance_mm=cfg.tolerance_mm)
    # the workers start (and load the scene) while this process reads the anatomy
    with Runner(cfg.workers, cfg.ray_address, warm=(str(sc.path), settings.__dict__)) as runner:
        t_an = time.perf_counter()
        anatomy, derived = read_anatomy(sc, names, pts, cfg, stock, kbound)
        space = make_space(cfg.bounds, stock, fixed, cfg.tubes, source=src,
                           derived=derived if cfg.derive else None)
        t_an = time.perf_counter() - t_an
        search, final = _search(runner, sc, names, pts, cfg, settings, fixed, stock, anatomy, space,
                                out, progress)
    return _finish(search, space, sc, names, pts, cfg, final, fixed, stock, anatomy, t0, t_an)


def _search(runner, sc, names, pts, cfg, settings, fixed, stock, anatomy, space, out, progress):
    """The search (:class:`~ctrplan.design.search.Search`) on ``runner``'s workers, then the
    final plans on the same workers; returns (search, final plans)."""
    from ctrplan import progress as _progress
    from ctrplan.design.search import STATE_FILE, Search

    plan_budget = cfg.plan_budget or max(4, min(24, cfg.budget // 6))
    state_path = Path(out) / STATE_FILE if out is not None else None
    if state_path is not None:
        state_path.parent.mkdir(parents=True, exist_ok=True)
    budget = cfg.budget
    if _ruled_out(anatomy, cfg, stock, fixed, space.k_max):
        # the anatomy rules out every target: one generation, to show the closest design
        budget = min(budget, cfg.generation)
        log.info("the anatomy rules out every target; searching one generation only")
    bar = _progress.bar(total=budget, desc="design", unit="design", disable=not progress)
    fit, starts = _starts(space, anatomy, sc)
    search = Search(space, str(sc.path), pts, settings, cfg.seed, budget, plan_budget,
                    cfg.generation, cfg.patience, cfg.time_limit, state_path, cfg.clearance_goal_mm,
                    _state_key(sc, names, pts, cfg, fixed), progress=bar.update,
                    plans_per_generation=cfg.plans_per_generation, starts=starts)
    final: dict = {}

    def finish(runner) -> None:
        t = time.perf_counter()
        final["out"] = _final_plans(search, space, sc, names, pts, cfg, runner)
        final["s"] = time.perf_counter() - t

    try:
        search.run(finish=finish, runner=runner)
    finally:
        bar.close()
    return search, final


def _final_plans(search, space, sc, names, pts, cfg, runner):
    """The chosen design, its plans per target (clearance objective; one job per target on
    the search's workers), its constraints."""
    from ctrplan.design.space import decode

    best = search.best()
    if best is None:
        return None, [], (), {}
    robot = decode(space, best["k"], np.array(best["u"]), name=f"design_{sc.name}").robot
    per = runner.map([search.job(robot, "final", [j]) for j in range(len(pts))])
    res = {k: [p[k][j] for j, p in enumerate(per)]
           for k in ("status", "reached", "clearance_mm", "clearance_estimate_mm", "tip_error_mm", "stable",
                     "results")}
    outcomes = []
    for j, n in enumerate(names):
        c = res["clearance_mm"][j]
        e = res["tip_error_mm"][j]
        est = res["clearance_estimate_mm"][j]
        outcomes.append(TargetOutcome(n, pts[j], bool(res["reached"][j]), res["status"][j],
                                      math.nan if c is None else float(c),
                                      math.nan if e is None else float(e), res["results"][j],
                                      math.nan if est is None else float(est)))
    constraints = constraint_report(robot, cfg.bounds)
    constraints["stability"] = {"satisfied": all(s is not False for s in res["stable"]),
                                "binds": any(s is False for s in res["stable"]),
                                "states_checked": int(sum(p["stability_states"] for p in per))}
    constraints["entry"] = {"satisfied": True, "binds": False}
    binding = tuple(k for k, v in constraints.items() if v["binds"])
    return robot, outcomes, binding, constraints


def _closest_json(ev: dict | None) -> dict | None:
    if ev is None:
        return None
    keys = ("index", "k", "robot", "parameters", "entry_ok", "entry_clearance_mm", "screen_passed",
            "screen_errors", "planned", "reached", "binding")
    out = {k: ev.get(k) for k in keys}
    out["tubes"] = out.pop("k")
    out["screen_errors_mm"] = out.pop("screen_errors")
    return out


def _finish(search, space, sc, names, pts, cfg, final, fixed, stock, anatomy, t0, t_an) -> DesignResult:
    from ctrplan.design.explain import explain

    robot, outcomes, binding, constraints = final.get("out", (None, [], (), {}))
    reached = sum(o.reached for o in outcomes)
    status = (DesignStatus.ALL_REACHED if outcomes and reached == len(outcomes)
              else DesignStatus.PARTIAL if reached else DesignStatus.NONE_REACHED)
    timings = {"anatomy": t_an, **search.timings}
    timings["final_plans"] = final.get("s", 0.0)
    blocked = explain(anatomy, cfg.bounds, stock, fixed, space.k_max, cfg.margin_mm or 0.0,
                      cfg.tolerance_mm, search.evaluations, outcomes or None)
    timings["total"] = time.perf_counter() - t0
    counts = {"evaluations": len(search.evaluations), "planned": search.planned,
              "resumed": search.resumed, "targets": len(pts), "generations": search.generations}
    if robot is not None:
        msg = f"{reached}/{len(pts)} targets reached by a {robot.n}-tube design"
    else:
        msg = f"0/{len(pts)} targets reached: no design was planned with success"
    if blocked:
        from collections import Counter

        why = Counter(b["blocking"] for b in blocked)
        msg += " (not reached: " + ", ".join(f"{n} by {k}" for k, n in why.most_common()) + ")"
    return DesignResult(success=status is DesignStatus.ALL_REACHED, status=status, message=msg,
                        robot=robot, targets=tuple(outcomes), evaluations=tuple(search.evaluations),
                        binding=binding, constraints=constraints, timings=timings, counts=counts,
                        seed=cfg.seed, scene=str(sc.path), time_cap_hit=search.time_cap_hit, config=cfg,
                        anatomy=anatomy.to_json(),
                        space=None if space.derived is None else space.derived.to_json(stock),
                        blocked=tuple(blocked), closest=_closest_json(search.closest()),
                        schedule=search.schedule)


class _CallableModule(types.ModuleType):
    """Makes ``ctrplan.design(...)`` call :func:`design` (the subpackage shares its name)."""

    def __call__(self, *args, **kwargs) -> DesignResult:
        return design(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
