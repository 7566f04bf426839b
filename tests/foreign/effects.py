"""Effect forms of the foreign generator (own forms, chosen OUTSIDE ctrplan's fitted families).

Every effect takes a parameter dict; ``{}`` gives the default magnitude; keys not given take
their defaults (except ``load``, see there). Each form below is written down with the reason why
ctrplan cannot represent it. Not only the family of the same name: ``diagnose`` fits several
families together (and nuisances on what they leave), so every form carries physics that NO
combination of ctrplan's families expresses (a crossing, a play, a contact, a history, a
frame): ``tests/test_foreign_forms.py`` fits each form with every family at once, from several
starts, nuisances included, and asserts that the best fit leaves at least twice the noise floor
of the statistics; ``tests/test_foreign_generator.py`` checks that the family of the same name
still removes most of it; ``tests/test_foreign_new_forms.py`` checks the newer parts against
oracles written there (scipy root on their fixed points, hand-composed rotations, plain loops).
The study (``core.STUDY_EFFECTS``) and the real-robot scenario (``scenarios.py``) set the newer
parts off explicitly (they keep the forms they were made with).

torsion       {"gj_scale": scalar or per tube, "coupling": [mm per tube],
               "play": [rad per tube], "play_torque": N mm}
              Truth = torsionally compliant Cosserat rods (GJ scaled), and each tube's drive
              coupling (collet, motor shaft) adds torsional compliance equal to ``coupling`` mm
              of extra tube behind the plane: psi_i(0) = alpha_i + (-beta_i + coupling_i) u_iz(0).
              The coupling also has play (backlash and a soft elastomer element): the tube's base
              turns within it by play_i tanh(T_i / play_torque) in the direction that relieves
              the torque T_i = GJ_i u_iz(0) it carries (a fixed point, damped). Absent =
              torsionally rigid truth. Default gj_scale (0.7, 0.45, 1.0) (tubes torsionally
              softer than the solid-tube formula: ground or cut walls), coupling (60, 40, 30) mm,
              play (0.1, 0.08, 0.05) rad, play_torque 0.3 N mm (outermost last).
              Why not ctrplan's: its torsion scales every tube's EI/GJ by one factor (tube 1 by a
              fixed extra factor); a length-independent coupling compliance is not a scale of the
              tube's compliance, and the play is a saturating rotation that follows the sign of
              each tube's torque (a square wave in the relative rotations): no family has a
              rotation that depends on the torque a tube carries.
clearance     {"amplitude": rad, "phase_deg": 205, "harmonics": [h0, h1, h2, ...],
               "lean": rad, "jump": mm or "gap", "snap": rad}
              Where outer tube j ends, the tubes inside it (relative rotation phi = inner - outer)
              (a) tilt in the inner tube's bending plane by
                  delta(phi) = amplitude * (h0 + h1 S(phi - phase) + sum_k>=2 h_k cos(k (phi -
                  phase))), S the gap crossing below (default amplitude 0.08, harmonics
                  [0.5, 0.3, 0.18]);
              (b) lean sideways, about the inner tube's bending direction, by
                  lean * sin(phi - phase) (the component of the moment mismatch out of the
                  inner tube's bending plane; default 0.007 rad);
              (c) jump laterally within the gap: the backbone is displaced by
                  jump * S(phi - phase) along the inner tube's bending direction (it lies against
                  the wall on the side of the moment; "gap" = the radial gap (id_outer -
                  od_inner) / 2 of the pair, 0.15 mm on seed1).
              S(x) = tanh(cos(x) / snap) / tanh(1 / snap) (``snap_wave``): the inner tube lies
              against one side of the gap or the other and crosses it within about ``snap``
              rad of the relative rotation where the moment mismatch changes sign (default
              0.3; 0 gives the smooth cos(x) of the earlier form).
              Off: amplitude 0, lean 0, jump 0.
              Why not ctrplan's: its harmonic forms tilt only about the inner tube's curvature
              axis (in-plane) with harmonics up to the second, its gap form tilts by a multiple
              of the curvature jump; the crossing's odd harmonics (third, fifth, ...), the lean
              out of the plane and the lateral jump are in no form of any family.
friction      {"form": "end_moment" | "coulomb_lag" | "presliding" | "stick_slip", ...}
              end_moment (the study's end moment, with friction growing with contact length):
              a torque T = s mu (|M| + contact M_c l_c / L_o) at the distal end of each
              outer tube o (|M| its bending moment there, M_c = EI_o EI_i / (EI_o + EI_i)
              |kappa_o - kappa_i| the moment scale of the contact with the tube i inside it,
              l_c its exposed length = the contact
              length with the tube inside it, L_o its length, s the sign of the relative rotation
              direction of the pair, inner minus outer), +T on the outer tube and -T on the inner
              one; with torsion in the Cosserat boundary conditions, without as the rotation
              correction dtheta = T l / GJ of each tube (l: its length from its base to that
              point).  {"mu": 0.03, "contact": 25.0}  (contact 0: the study's form)
              Why not ctrplan's: its end_moment torque is mu |M| (no term growing with the
              exposed length), its lag forms constant angles.
              coulomb_lag: each tube's transmitted rotation lags its command in the direction of
              its last motion by an angle that grows with the CONTACT: the part of the tube's
              pre-curved section held inside the tubes around it (proximal of the distal end
              of the next outer tube; of the base plane for the outermost tube) presses
              against their walls, and that normal force is what friction acts on, and with the
              contact FORCE (torque-dependent friction): alpha_eff = alpha - d c,
              c = lag (1 + growth h) (1 + moment (2 r - 1)), h in [0, 1] the held fraction of
              the curved section (0 while it is all exposed; for inner tubes it follows the
              translation relative to the next outer tube, with kinks where the curved section
              starts and stops being held), r = |kappa_i e(alpha_i) - kappa_o e(alpha_o)| /
              (kappa_i + kappa_o) the pair's curvature mismatch at its relative rotation (the
              force between them; 1/2 for the outermost tube). Default {"lag": 0.12 rad,
              "growth": 2.0, "moment": 0.5, "beta_lag": 0 mm} ("lag" scalar or per tube).
              Why not ctrplan's: its lag / relative / dead_band lags are constant per tube, or
              grow with the square of the tube's own retracted fraction (its windup, lost +
              wind (-beta / L)^2): h depends on the neighbour's translation and is piecewise
              linear with kinks, and no lag depends on the relative rotation.
              presliding: the lag builds up over a rotation after each reversal with a Dahl
              exponent 2 (hyperbolic, not exponential): w = 1 - z d / c, w <- w / (1 + w
              |dalpha| / angle), z = c d (1 - w), c as for coulomb_lag;
              alpha_eff = alpha - z. Without row history (``backbones(direction=...)``) the fully
              developed lag c d. Default {"lag": 0.18 rad, "angle": 0.3 rad, "growth": 2.0,
              "moment": 0.6}.
              Why not ctrplan's: its presliding recursion is the exponential one
              (w <- w exp(-|dalpha| / angle)) with a lag constant or growing with the own
              retracted fraction squared.
              stick_slip: static friction above kinetic friction: along the rows each tube's
              transmitted angle sticks while its lag stays within the static limit c (as for
              coulomb_lag: it grows with the contact and its force, torque-dependent), and where
              the command pushes it beyond, slips until the lag is the kinetic ``kinetic c``,
              sticks again, and so on (a sawtooth over the commanded travel; each sweep starts
              settled). Without row history the mean lag (1 + kinetic) c / 2. Default
              {"lag": 0.15 rad, "kinetic": 0.75, "growth": 2.0, "moment": 0.4}.
              Why not ctrplan's: no form has a lag that saws between two limits along the
              commanded travel.
precurvature  {"scale": [per tube], "ramp": [per tube], "twist": [rad per tube],
               "relax": [per tube], "relax_turns": turns, "kink": [rad per tube], "kink_at":
               fraction, "kink_length": mm}
              kappa_i(s) = scale_i kappa_i (1 + ramp_i (s_c - 1/2)), s_c in [0, 1] along the
              curved section from its proximal start (held constant over equal
              sub-sections, 8: a shape-setting fixture that bends more at one end); the curve is
              not planar: in the tube's frame its plane turns by twist_i (s_c - 1/2) (a helix,
              the fixture's mandrel twisted); and it relaxes with use: times 1 - relax_i (1 -
              exp(-N_i / relax_turns)), N_i the bending cycles the tube has gone through (its
              accumulated rotation relative to the tube around it, in turns, counted along the
              rows in order; rows without order: relaxed); optionally a kink (a concentrated
              bend of ``kink`` rad over ``kink_length`` mm at the fraction ``kink_at`` of the
              section; off by default). Default scale (0.88, 1.14, 0.90), ramp (0.6, -0.6, 0.6),
              twist (1.0, -1.1, 1.0) rad, relax (0.06, 0.08, 0.05) over 3 turns (outermost
              last).
              Why not ctrplan's: it scales each tube's precurvature by one constant, in a plane;
              the out-of-plane part of the twisted curve turns with the tube and depends on how
              much of the section is exposed, and the relaxation is a history.
stiffness     {"scale": [per tube], "curved": [per tube], "torsion": [per tube],
               "soften": [per tube], "soften_onset": strain, "soften_width": strain}
              E_i -> scale_i E_i in bending, times ``curved_i`` over the curved (shape-set,
              heat-treated) section; GJ_i -> torsion_i GJ_i (only with torsion); and
              superelastic softening: nitinol's stress-strain curve bends over (R-phase, then the
              stress-induced martensite plateau), so a tube's secant bending stiffness drops
              where its bending strain is large, EI_i -> EI_i (1 - soften / (1 + exp(-(eps -
              onset) / width))), eps = (od_i / 2) |u_i - kappa_i| per segment (the strain of
              the torsionally rigid shape; a fixed point, ``mechanics.soften``).
              Default scale (1.0, 1.5, 0.7), curved (1.25, 0.8, 1.0), torsion (1.0, 0.8, 1.1),
              soften 0.6 with onset 0.45 % and width 0.1 % strain.
              Why not ctrplan's: its ratios are one bending stiffness per tube, the same on the
              straight and the curved section (and GJ follows EI), and none depends on the strain.
load          {"gravity": [gx, gy, gz] m/s^2 in the base frame (default [9.81, 0, 0]:
              horizontal robot), "density": [kg/m^3 per tube] (default: the robot file's
              ``density`` or nitinol 6450), "tip_force": [Fx, Fy, Fz] N (default "auto":
              (0, -1e-5 EI_1, 0) N, EI_1 of the innermost tube in N mm^2), "lumen_density":
              kg/m^3 of what fills the innermost tube's lumen (a wire, a fibre, fluid; default
              2500), "tether": N/mm (default 1.5e-4) and "anchor": [3] mm (default "auto":
              (0.15, 0, 1.0) L_1): a cable (the tracker sensor's lead, a tissue attachment)
              pulls the tip toward the anchor with F = tether (anchor - tip) (fixed point in the
              tip), "base_compliance": rad per N mm (default 5e-4): the mount turns the whole
              robot about the base origin by that times the loads' bending moment there,
              "wall": N/mm (default 6e-3), "wall_normal": [3] (default (-1, 0, 0)), "wall_at":
              mm (default "auto": -0.08 L_1): soft tissue the tip presses on, a plane
              {p: normal . p = wall_at}; where the tip is beyond it, it pushes back along the
              normal with wall times the depth (a fixed point in the tip, damped)}.
              The defaults apply to {} only: with any key given, the keys not given are absent
              (gravity None, no tip force, empty lumen, no tether, rigid mount, no wall), e.g.
              {"gravity": [0, -9.81, 0]} is gravity alone.
              Why not ctrplan's: its loads are a constant gravity (times each tube's density
              from the robot file, one scale for all tubes) and a constant tip force (all three
              components). The tether's pull is nearly constant over a workspace (a constant
              tip force takes in all but 0.02 mm of it) and the filled lumen is nearly a larger
              g; the compliant mount turns the robot by the loads' moment, which changes with
              the configuration, and the wall's force is a hinge of the tip's position: zero on
              one side of the plane, growing with the depth on the other.
joint_offset  {"alpha": [rad per tube], "beta": [mm per tube], "periodic": [rad per tube],
               "periodic_phase": [rad per tube], "beta_scale": [per tube], "gear": [rad per
               tube], "gear_order": k, "gear_phase": [rad per tube], "rehome": [rad, mm],
               "rehome_seed": int or None}
              true alpha = alpha + offset + periodic sin(alpha + periodic_phase) (an eccentric
              encoder: a once-per-turn error) + gear sin(k alpha + gear_phase) (the drive's
              transmission error, once per tooth of a k-tooth pinion), true beta = (1 +
              beta_scale) beta + offset (a lead screw pitch error); the robot homes its joints
              before every sweep and the home switches repeat to ``rehome`` (standard deviation
              of a per-sweep offset of every rotation, rad, and translation, mm; drawn from
              ``rehome_seed``, which ``generate`` draws from its seed when None). Default
              periodic (0.03, 0.025, 0.02) rad, beta_scale (0.01, -0.008, 0.006), gear
              (0.03, 0.025, 0.02) rad with k = 12, rehome (0.01 rad, 0.2 mm).
              Why not ctrplan's: it fits constant offsets only; a twelve-per-turn error of each
              rotation is no smooth function of the configuration or the tip's position, and
              offsets that change from sweep to sweep are none of the configuration.
registration  {"rotvec": [rad x3], "translation": [mm x3], "scale": [x3] or scalar,
               "mount": [rad, rad], "sensor": [mm x3]}
              sensor = (1 + scale) * (Rot(rotvec) Rot(m(q)) coil + t) per sensor axis (a tracker
              whose scale is off by a fraction of a percent), where the coil sits ``sensor`` mm
              from the tip in the innermost tube's frame (x toward its bending direction, z along
              the tangent: a coil glued on the side of the tube, behind its tip), and m(q) turns
              the robot's housing with its configuration (``mount_rotvec``: its clamp rocks to
              the side of the unbalanced outer rotary stage, a bowed rail pitches it along the
              outer carriage's travel). Default scale (0.012, -0.008, 0.015), mount (0.01,
              0.008) rad, sensor (0, 0.9, 0) mm (beside the axis, across the bending plane).
              Why not ctrplan's: its registration is rigid (no scale); the coil's offset turns
              with the tip's frame (no function of the tip's position) and the housing turns with
              the joints (no constant transform).
distortion    {"form": "bumps" | "dipole", "amplitude": mm, "width": mm or "auto",
               "centres": [[3] x k] mm or "auto", "vectors": [[3] x k] or "auto"}
              bumps: a rough tracker-field warp (metal parts near the field generator):
              p + amplitude sum_k v_k exp(-|p - c_k|^2 / (2 width^2)), v_k unit vectors; "auto":
              36 centres on a grid over the workspace (spacing 0.1 L_1, :func:`distortion_grid`),
              width 0.05 L_1 (L_1 the innermost tube's length, 16 mm on seed1); default amplitude
              2.8 mm. dipole: a piece of metal beside the workspace, p + amplitude (w / r)^3
              (3 (m . rhat) rhat - m) / 2, r = |p - c| softened by w / 4, one centre and moment
              (:func:`dipole_source`: 0.2, -0.12, 0.55 L_1), w the width (auto 0.12 L_1),
              default amplitude 10 mm (``DIPOLE_AMPLITUDE``).
              Why not ctrplan's nuisance: its field is a quadratic polynomial of the measured
              position; a field varying over ~16 mm inside a ~100 mm workspace is not, nor is a
              1 / r^3 field whose source is a few tens of mm from the tips.
drift         {"amplitude": mm, "direction": [3], "settle": 0.15, "step": mm, "step_at": 0.6,
               "step_direction": [3], "wobble": mm, "wobble_period": 0.04,
               "wobble_direction": [3], "wander": mm, "wander_time": 0.005,
               "wander_seed": int or None}  sensor drift: an exponential settling
              amplitude (1 - exp(-t / tau)) / (1 - exp(-1 / tau)) along ``direction``
              (t the fraction of the recording time, tau = settle), a fast cycle
              wobble sin(2 pi t / wobble_period) along ``wobble_direction`` (a field generator's
              cooling cycle; default 0.5 mm), a step of ``step`` mm at t >= step_at (the
              tracker was bumped), and a wander: a smooth random offset of ``wander`` mm rms per
              axis that changes over ``wander_time`` of the recording (:func:`wander`; drawn from
              ``wander_seed``, which ``generate`` draws from its seed when None; default 0.25
              mm).
              Why not ctrplan's nuisance: it fits a linear spline in the fraction of the
              recording time with 10 evenly spaced knots (a cycle of 1/25 of the recording and a
              wander over 1/200 of it are far faster than its knots, and a step is not
              continuous).
"""

from __future__ import annotations

import copy

import numpy as np

VOCAB_EFFECTS = ("torsion", "clearance", "friction", "precurvature", "stiffness", "load",
                 "joint_offset", "registration")
OUTSIDE_EFFECTS = ("distortion", "drift")
FRICTION_FORMS = ("end_moment", "coulomb_lag", "presliding", "stick_slip")
DISTORTION_FORMS = ("bumps", "dipole")
#: the dipole distortion's default amplitude (mm at distance ``width`` on its axis; its mean
#: displacement over the tips of seed1's sweeps is about 1.4 mm)
DIPOLE_AMPLITUDE = 10.0


def _per_tube(v, n, name):
    a = np.asarray(v, float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"effect parameter {name!r} needs {n} values, got {a.shape}")
    return a


def _alt(n, first, a, b):
    return [first] + [a if i % 2 == 1 else b for i in range(1, n)]


def _outer_last(n, inner, mid, outer):
    """Per-tube values with the innermost ``inner``, the outermost ``outer`` and ``mid`` between
    (two tubes: inner, outer)."""
    if n == 1:
        return [inner]
    return [inner] + [mid] * (n - 2) + [outer]


def defaults(name: str, n: int, spec=None) -> dict:
    """Default parameters (each moves the tip by a few mm on the shipped robots)."""
    if name == "torsion":
        return {"gj_scale": _outer_last(n, 0.7, 0.45, 1.0), "coupling": _outer_last(n, 60.0, 40.0, 30.0),
                "play": _outer_last(n, 0.1, 0.08, 0.05), "play_torque": 0.3}
    if name == "clearance":
        return {"amplitude": 0.08, "phase_deg": 205.0, "harmonics": [0.5, 0.3, 0.18],
                "lean": 0.007, "jump": "gap", "snap": 0.3}
    if name == "friction":
        return friction_defaults("end_moment")
    if name == "precurvature":
        return {"scale": _alt(n, 0.88, 1.14, 0.90), "ramp": _alt(n, 0.6, -0.6, 0.6),
                "twist": _alt(n, 1.0, -1.1, 1.0), "relax": _alt(n, 0.06, 0.08, 0.05),
                "relax_turns": 3.0, "kink": 0.0, "kink_at": 0.6, "kink_length": 3.0}
    if name == "stiffness":
        return {"scale": _alt(n, 1.0, 1.5, 0.7), "curved": _alt(n, 1.25, 0.8, 1.0),
                "torsion": _alt(n, 1.0, 0.8, 1.1), "soften": 0.6, "soften_onset": 0.0045,
                "soften_width": 0.001}
    if name == "load":
        return {"gravity": [9.81, 0.0, 0.0], "density": None, "tip_force": "auto",
                "lumen_density": 2500.0, "tether": 1.5e-4, "anchor": "auto",
                "base_compliance": 5e-4, "wall": 6e-3, "wall_normal": [-1.0, 0.0, 0.0],
                "wall_at": "auto"}
    if name == "joint_offset":
        return {"alpha": _alt(n, 0.05, -0.06, 0.04), "beta": _alt(n, -1.5, -1.0, -0.5),
                "periodic": _alt(n, 0.03, 0.025, 0.02), "periodic_phase": _alt(n, 0.7, 2.1, -1.3),
                "beta_scale": _alt(n, 0.01, -0.008, 0.006), "gear": _alt(n, 0.03, 0.025, 0.02),
                "gear_order": 12, "gear_phase": _alt(n, 0.3, 1.9, -0.8),
                "rehome": [0.01, 0.2], "rehome_seed": None}
    if name == "registration":
        return {"rotvec": [0.012, -0.009, 0.015], "translation": [1.2, -0.9, 1.5],
                "scale": [0.012, -0.008, 0.015], "mount": [0.01, 0.008],
                "sensor": [0.0, 0.9, 0.0]}
    if name == "distortion":
        return {"form": "bumps", "amplitude": 2.8, "width": "auto", "centres": "auto",
                "vectors": "auto"}
    if name == "drift":
        return {"amplitude": 4.0, "direction": [0.6, -0.48, 0.64], "settle": 0.15, "step": 1.5,
                "step_at": 0.6, "step_direction": [-0.5, 0.7, 0.5], "wobble": 0.5,
                "wobble_period": 0.04, "wobble_direction": [0.3, 0.9, -0.3], "wander": 0.25,
                "wander_time": 0.005, "wander_seed": None}
    raise ValueError(f"unknown effect {name!r}; known: {VOCAB_EFFECTS + OUTSIDE_EFFECTS}")


def friction_defaults(form: str) -> dict:
    if form == "end_moment":
        return {"form": form, "mu": 0.03, "contact": 25.0}
    if form == "coulomb_lag":
        return {"form": form, "lag": 0.12, "beta_lag": 0.0, "growth": 2.0, "moment": 0.5}
    if form == "presliding":
        return {"form": form, "lag": 0.18, "angle": 0.3, "growth": 2.0, "moment": 0.6}
    if form == "stick_slip":
        return {"form": form, "lag": 0.15, "kinetic": 0.75, "growth": 2.0, "moment": 0.4}
    raise ValueError(f"unknown friction form {form!r}; known: {FRICTION_FORMS}")


def distortion_grid(L1: float) -> tuple[list, list]:
    """The "auto" distortion: centres on a grid over the workspace, x, y in {-0.1, 0, 0.1} L_1,
    z in {0.5, 0.6, 0.7, 0.8} L_1 (sensor frame), and fixed pseudo-random displacement directions
    (numpy default_rng(12345), normalised)."""
    g = (-0.1, 0.0, 0.1)
    C = np.array([(x, y, z) for x in g for y in g for z in (0.5, 0.6, 0.7, 0.8)]) * L1
    V = np.random.default_rng(12345).normal(size=C.shape)
    return C.tolist(), V.tolist()


def dipole_source(L1: float) -> tuple[list, list]:
    """The "auto" dipole distortion: one source beside the workspace, at (0.2, -0.12, 0.55) L_1
    (sensor frame), its moment along (0.3, 0.8, -0.52) (normalised)."""
    return [[0.2 * L1, -0.12 * L1, 0.55 * L1]], [[0.3, 0.8, -0.52]]


def resolve(effects, n: int, spec=None) -> dict:
    """Fill in defaults; returns a new dict name -> full parameters. ``tip_force: "auto"``
    (the load default) becomes (0, -1e-5 EI_1, 0) N with EI_1 the innermost tube's bending
    stiffness in N mm^2 (0.055 N on seed1, 0.27 N on two_tube_nylon); the clearance
    ``jump: "gap"`` becomes the radial gap of the first pair, the distortion's "auto" centres and
    width are placed from the innermost tube's length. Idempotent."""
    out = {}
    for name, params in (effects or {}).items():
        params = dict(params or {})
        if name == "friction":
            base = friction_defaults(params.get("form", "end_moment"))
        else:
            base = defaults(name, n)
        unknown = set(params) - set(base)
        if unknown:
            raise ValueError(f"effect {name!r}: unknown parameter(s) {sorted(unknown)}")
        if name == "load" and params:
            # explicit loads: what is not given is absent (a gravity-only or force-only load)
            base = {"gravity": None, "density": None, "tip_force": None, "lumen_density": None,
                    "base_compliance": None, "tether": None, "anchor": "auto", "wall": None,
                    "wall_normal": [-1.0, 0.0, 0.0], "wall_at": "auto"}
        base.update(params)
        if name == "load" and isinstance(base.get("tip_force"), str):
            if base["tip_force"] != "auto" or spec is None:
                raise ValueError("load: tip_force must be a 3-vector (N), None or 'auto'")
            base["tip_force"] = [0.0, -1e-5 * float(spec.EI[0]), 0.0]
        if name == "clearance" and isinstance(base.get("jump"), str):
            if base["jump"] != "gap":
                raise ValueError("clearance: jump must be a number (mm) or 'gap'")
            base["jump"] = (0.5 * float(spec.id[1] - spec.od[0])
                            if spec is not None and n > 1 else 0.0)
        if name == "load" and isinstance(base.get("anchor"), str):
            if base["anchor"] != "auto":
                raise ValueError("load: anchor must be a 3-vector (mm) or 'auto'")
            L1 = float(spec.L[0]) if spec is not None else 300.0
            base["anchor"] = [0.15 * L1, 0.0, 1.0 * L1]
        if name == "load" and isinstance(base.get("wall_at"), str):
            if base["wall_at"] != "auto":
                raise ValueError("load: wall_at must be a number (mm) or 'auto'")
            base["wall_at"] = -0.08 * (float(spec.L[0]) if spec is not None else 300.0)
        if name == "distortion":
            L1 = float(spec.L[0]) if spec is not None else 300.0
            if base.get("form", "bumps") not in DISTORTION_FORMS:
                raise ValueError(f"distortion: form must be one of {DISTORTION_FORMS}")
            if isinstance(base.get("width"), str):
                base["width"] = 0.05 * L1 if base.get("form", "bumps") == "bumps" else 0.12 * L1
            if base.get("form") == "dipole" and "amplitude" not in params:
                base["amplitude"] = DIPOLE_AMPLITUDE
            C, V = distortion_grid(L1) if base.get("form", "bumps") == "bumps" else dipole_source(L1)
            if isinstance(base.get("centres"), str):
                base["centres"] = C
            if isinstance(base.get("vectors"), str):
                base["vectors"] = V
        out[name] = copy.deepcopy(base)
    return out


def snap_wave(x, snap: float):
    """cos(x), or with ``snap`` > 0 the saturated crossing tanh(cos(x) / snap) / tanh(1 / snap):
    +-1 over most of the turn, changing sign within about ``snap`` rad of cos(x) = 0."""
    c = np.cos(x)
    if not snap:
        return c
    return np.tanh(c / snap) / np.tanh(1.0 / snap)


def clearance_fn(params):
    """callable(phi, pair) -> (tilt_in, tilt_out, jump_b, jump_a) (see the module docstring)."""
    amp = float(params["amplitude"])
    ph = np.deg2rad(float(params["phase_deg"]))
    h = np.asarray(params["harmonics"], float)
    lean = float(params.get("lean", 0.0))
    jump = float(params.get("jump", 0.0) or 0.0)
    snap = float(params.get("snap", 0.0) or 0.0)

    def event(phi, pair):
        d = np.zeros_like(phi)
        for k, hk in enumerate(h):
            d = d + hk * (snap_wave(phi - ph, snap) if k == 1 else np.cos(k * (phi - ph)))
        if lean == 0.0 and jump == 0.0:
            return amp * d
        return (amp * d, lean * np.sin(phi - ph), jump * snap_wave(phi - ph, snap),
                np.zeros_like(phi))
    return event


def rotation_matrix(rotvec) -> np.ndarray:
    v = np.asarray(rotvec, float)
    th = np.linalg.norm(v)
    if th == 0:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _unit(v):
    v = np.asarray(v, float)
    nv = np.linalg.norm(v)
    return v / nv if nv > 0 else v


def wander(params, tfrac: np.ndarray) -> np.ndarray:
    """(N, 3) the drift's wandering part at time fractions ``tfrac``: a smooth random process
    (white noise on a grid of ``wander_time`` / 4 spacing over the recording, smoothed by a
    Gaussian of ``wander_time``, scaled to ``wander`` mm rms per axis), drawn from
    ``wander_seed``."""
    amp = float(params.get("wander", 0.0) or 0.0)
    if not amp:
        return np.zeros((len(tfrac), 3))
    tau = float(params["wander_time"])
    h = tau / 4.0
    pad = 4.0 * tau
    grid = np.arange(-pad, 1.0 + pad + h, h)
    rng = np.random.default_rng([int(params.get("wander_seed") or 0), 31337])
    w = rng.normal(size=(grid.size, 3))
    k = np.exp(-0.5 * (np.arange(-16, 17) * h / tau) ** 2)
    sm = np.stack([np.convolve(w[:, j], k / k.sum(), mode="same") for j in range(3)], axis=1)
    inside = (grid >= 0.0) & (grid <= 1.0)
    sm = sm / sm[inside].std(axis=0) * amp
    t = np.asarray(tfrac, float)
    return np.stack([np.interp(t, grid, sm[:, j]) for j in range(3)], axis=1)


def mount_rotvec(params, q: np.ndarray, spec) -> np.ndarray:
    """(N, 3) rotation vector of the robot's housing in the tracker frame (the registration's
    configuration-dependent part): ``mount`` = (unbalance, rail) rad. The outermost tube's
    rotary stage is unbalanced and the housing's clamp has play: the housing rocks about x to
    the side the stage's heavy side is on, unbalance tanh(cos(alpha_n - 0.4) / 0.2) / tanh(5)
    (:func:`snap_wave`); its carriage rides a bowed rail: the housing pitches by rail sin(pi u)
    about y, u the carriage's fraction of its travel."""
    m = np.broadcast_to(np.asarray(params.get("mount", 0.0) or 0.0, float), (2,))
    q = np.atleast_2d(np.asarray(q, float))
    n = spec.n
    a = q[:, n - 1]
    lo = max(float(spec.beta_lo[-1]), -float(spec.L[-1]))
    u = np.clip((q[:, 2 * n - 1] - lo) / (0.0 - lo), 0.0, 1.0)
    return np.stack([m[0] * snap_wave(a - 0.4, 0.2), m[1] * np.sin(np.pi * u), np.zeros_like(a)],
                    axis=1)


def drift_offset(params, tfrac: np.ndarray) -> np.ndarray:
    """(N, 3) drift offset at time fractions ``tfrac`` (see the module docstring)."""
    t = np.asarray(tfrac, float)
    tau = float(params.get("settle", 0.0))
    if tau > 0:
        shape = (1.0 - np.exp(-t / tau)) / (1.0 - np.exp(-1.0 / tau))
    else:
        shape = t
    off = float(params["amplitude"]) * shape[:, None] * _unit(params["direction"])[None, :]
    wob = float(params.get("wobble", 0.0))
    if wob:
        ph = 2.0 * np.pi * t / float(params["wobble_period"])
        off = off + wob * np.sin(ph)[:, None] * _unit(params["wobble_direction"])[None, :]
    step = float(params.get("step", 0.0))
    if step:
        off = off + step * (t >= float(params["step_at"]))[:, None] * \
            _unit(params["step_direction"])[None, :]
    return off


def sensor(p: np.ndarray, eff: dict, tfrac: np.ndarray | None, q=None, spec=None) -> np.ndarray:
    """Apply tracker effects (registration, distortion, drift) to points (..., 3); tfrac (N,)
    the fraction of the recording time elapsed per row (drift), or None (no drift); q (N, 2n)
    and spec: the commanded configurations and robot (the registration's mount)."""
    out = p
    if "registration" in eff:
        rg = eff["registration"]
        if np.any(np.asarray(rg.get("mount", 0.0) or 0.0, float) != 0.0):
            if q is None or spec is None:
                raise ValueError("registration: the mount needs the configurations")
            Rm = np.stack([rotation_matrix(r) for r in mount_rotvec(rg, q, spec)])
            out = np.einsum("bij,b...j->b...i", Rm, out)
        R = rotation_matrix(rg["rotvec"])
        out = out @ R.T + np.asarray(rg["translation"], float)
        sc = np.broadcast_to(np.asarray(rg.get("scale", 0.0), float), (3,))
        if np.any(sc != 0.0):
            out = out * (1.0 + sc)
    if "distortion" in eff:
        ds = eff["distortion"]
        A = float(ds["amplitude"])
        if A != 0.0:
            C = np.asarray(ds["centres"], float).reshape(-1, 3)
            V = np.stack([_unit(v) for v in np.asarray(ds["vectors"], float).reshape(-1, 3)])
            w = float(ds["width"])
            if ds.get("form", "bumps") == "dipole":
                out = out + A * dipole(out, C[0], V[0], w)
            else:
                d2 = np.sum((out[..., None, :] - C) ** 2, axis=-1)          # (..., k)
                wgt = np.exp(-0.5 * d2 / w ** 2)
                out = out + A * (wgt @ V[: C.shape[0]])
    if "drift" in eff and tfrac is not None:
        off = drift_offset(eff["drift"], tfrac) + wander(eff["drift"], tfrac)
        out = out + (off[:, None, :] if out.ndim == 3 else off)
    return out


def dipole(p: np.ndarray, c: np.ndarray, m: np.ndarray, w: float) -> np.ndarray:
    """(..., 3) displacement of a dipole-like field distortion (a piece of metal beside the
    workspace): (w / r)^3 (3 (m . rhat) rhat - m) / 2, r = |p - c| softened by w / 4 (1 at
    distance w on the moment's axis)."""
    r = p - c
    r2 = np.sum(r * r, axis=-1, keepdims=True) + (0.25 * w) ** 2
    rn = np.sqrt(r2)
    rh = r / rn
    return 0.5 * (w / rn) ** 3 * (3.0 * np.sum(rh * m, axis=-1, keepdims=True) * rh - m)
