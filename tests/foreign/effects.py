"""Effect forms of the foreign generator (own forms; deliberately not ctrplan's).

Every effect takes a parameter dict; ``{}`` gives the default magnitude. Parameters:

torsion       {"gj_scale": 1.0}  truth = torsionally compliant Cosserat rods (GJ scaled); absent =
              torsionally rigid truth.
clearance     {"amplitude": rad, "phase_deg": 205, "harmonics": [h0, h1, h2, ...]}
              At the distal end of each outer tube the inner tube's tangent tilts by
              delta(phi) = amplitude * sum_k h_k cos(k (phi - phase)), phi = relative rotation
              (inner - outer, local angles where the outer tube ends), toward the inner tube's
              bending direction. Default harmonics [0.5, 0.5]: delta = A (1 + cos(phi - phase))/2,
              largest at phase (205 deg, the study's), zero opposite it.
friction      {"form": "end_moment" | "coulomb_lag" | "presliding", ...}
              end_moment (the study's): a torque T = mu * s * |M| at the distal end of each outer
              tube (|M| its bending moment there, s = sign of the relative rotation direction of
              the pair, inner minus outer), +T on the outer tube and -T on the inner one. With
              torsion it enters the Cosserat boundary conditions (the study's beta'(L) =
              mu'|M|(1/k2z - 1/k1z)); without torsion as the rotation correction dtheta of each
              tube, T l / GJ (l: the tube's length from its base to that point), sign following
              the direction of relative rotation.  {"mu": ...}
              coulomb_lag: each tube's transmitted rotation lags its command by a constant
              angle in the direction of its last motion: alpha_eff = alpha - lag * d.
              {"lag": rad (scalar or per tube), "beta_lag": mm (scalar or per tube, default 0)}
              presliding: the lag builds up over a rotation after each reversal (Dahl-like):
              z <- c d + (z - c d) exp(-|dalpha| / angle); alpha_eff = alpha - z. Without row
              history (``backbones(direction=...)``) the fully developed lag c d is used.
              {"lag": rad, "angle": rad}
precurvature  {"scale": [per tube]}  kappa_i -> scale_i kappa_i
stiffness     {"scale": [per tube]}  E_i -> scale_i E_i (bending and torsion)
load          {"gravity": [gx, gy, gz] m/s^2 in the base frame (default [9.81, 0, 0]:
              horizontal robot), "density": [kg/m^3 per tube] (default: the robot file's
              ``density`` or nitinol 6450), "tip_force": [Fx, Fy, Fz] N (default "auto":
              (0, -1e-5 EI_1, 0) N, EI_1 of the innermost tube in N mm^2)}. The defaults apply
              to {} only: with any key given, the keys not given are absent (gravity None, no
              tip force), e.g. {"gravity": [0, -9.81, 0]} is gravity alone.
joint_offset  {"alpha": [rad per tube], "beta": [mm per tube]}  true q = commanded q + offset
registration  {"rotvec": [rad x3], "translation": [mm x3]}  sensor = Rot(rotvec) base + t
distortion    {"amplitude": mm, "wavelength": mm}  smooth nonlinear tracker-field warp
              p + A [sin(2 pi (y + z/2)/lam + .4), sin(2 pi (z + x/2)/lam + 1.3),
                     sin(2 pi (x + y/2)/lam + 2.1)]  (not a rigid transform)
drift         {"amplitude": mm, "direction": [3]}  slow sensor drift: offset growing linearly in
              time from 0 at the first row to ``amplitude`` at the last row
"""

from __future__ import annotations

import copy

import numpy as np

VOCAB_EFFECTS = ("torsion", "clearance", "friction", "precurvature", "stiffness", "load",
                 "joint_offset", "registration")
OUTSIDE_EFFECTS = ("distortion", "drift")
FRICTION_FORMS = ("end_moment", "coulomb_lag", "presliding")


def _per_tube(v, n, name):
    a = np.asarray(v, float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"effect parameter {name!r} needs {n} values, got {a.shape}")
    return a


def _alt(n, first, a, b):
    return [first] + [a if i % 2 == 1 else b for i in range(1, n)]


def defaults(name: str, n: int, spec=None) -> dict:
    """Default parameters (each moves the tip by a few mm on the shipped robots)."""
    if name == "torsion":
        return {"gj_scale": 1.0}
    if name == "clearance":
        return {"amplitude": 0.065, "phase_deg": 205.0, "harmonics": [0.5, 0.5]}
    if name == "friction":
        return {"form": "end_moment", "mu": 0.08}
    if name == "precurvature":
        return {"scale": _alt(n, 0.92, 1.10, 0.93)}
    if name == "stiffness":
        return {"scale": _alt(n, 1.0, 1.3, 0.85)}
    if name == "load":
        return {"gravity": [9.81, 0.0, 0.0], "density": None, "tip_force": "auto"}
    if name == "joint_offset":
        return {"alpha": _alt(n, 0.05, -0.06, 0.04), "beta": _alt(n, -1.5, -1.0, -0.5)}
    if name == "registration":
        return {"rotvec": [0.012, -0.009, 0.015], "translation": [1.2, -0.9, 1.5]}
    if name == "distortion":
        return {"amplitude": 2.0, "wavelength": 220.0}
    if name == "drift":
        return {"amplitude": 4.0, "direction": [0.6, -0.48, 0.64]}
    raise ValueError(f"unknown effect {name!r}; known: {VOCAB_EFFECTS + OUTSIDE_EFFECTS}")


def friction_defaults(form: str) -> dict:
    if form == "end_moment":
        return {"form": form, "mu": 0.08}
    if form == "coulomb_lag":
        return {"form": form, "lag": 0.05, "beta_lag": 0.0}
    if form == "presliding":
        return {"form": form, "lag": 0.06, "angle": 0.25}
    raise ValueError(f"unknown friction form {form!r}; known: {FRICTION_FORMS}")


def resolve(effects, n: int, spec=None) -> dict:
    """Fill in defaults; returns a new dict name -> full parameters. ``tip_force: "auto"``
    (the load default) becomes (0, -1e-5 EI_1, 0) N with EI_1 the innermost tube's bending
    stiffness in N mm^2 (0.055 N on seed1, 0.27 N on two_tube_nylon)."""
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
            base = {"gravity": None, "density": None, "tip_force": None}
        base.update(params)
        if name == "load" and isinstance(base.get("tip_force"), str):
            if base["tip_force"] != "auto" or spec is None:
                raise ValueError("load: tip_force must be a 3-vector (N), None or 'auto'")
            base["tip_force"] = [0.0, -1e-5 * float(spec.EI[0]), 0.0]
        out[name] = copy.deepcopy(base)
    return out


def clearance_fn(params):
    amp = float(params["amplitude"])
    ph = np.deg2rad(float(params["phase_deg"]))
    h = np.asarray(params["harmonics"], float)

    def delta(phi, pair):
        d = np.zeros_like(phi)
        for k, hk in enumerate(h):
            d = d + hk * np.cos(k * (phi - ph))
        return amp * d
    return delta


def rotation_matrix(rotvec) -> np.ndarray:
    v = np.asarray(rotvec, float)
    th = np.linalg.norm(v)
    if th == 0:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def sensor(p: np.ndarray, eff: dict, tfrac: np.ndarray | None) -> np.ndarray:
    """Apply tracker effects (registration, distortion, drift) to points (..., 3); tfrac (N,)
    the fraction of the recording time elapsed per row (drift), or None (no drift)."""
    out = p
    if "registration" in eff:
        R = rotation_matrix(eff["registration"]["rotvec"])
        out = out @ R.T + np.asarray(eff["registration"]["translation"], float)
    if "distortion" in eff:
        A = float(eff["distortion"]["amplitude"])
        lam = float(eff["distortion"]["wavelength"])
        x, y, z = out[..., 0], out[..., 1], out[..., 2]
        w = 2 * np.pi / lam
        d = np.stack([np.sin(w * (y + 0.5 * z) + 0.4), np.sin(w * (z + 0.5 * x) + 1.3),
                      np.sin(w * (x + 0.5 * y) + 2.1)], axis=-1)
        out = out + A * d
    if "drift" in eff and tfrac is not None:
        dvec = np.asarray(eff["drift"]["direction"], float)
        dvec = dvec / np.linalg.norm(dvec)
        off = float(eff["drift"]["amplitude"]) * tfrac[:, None] * dvec[None, :]
        out = out + (off[:, None, :] if out.ndim == 3 else off)
    return out
