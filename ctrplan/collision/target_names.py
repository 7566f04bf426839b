"""Anatomical names of the shipped scenes' example targets (``t01``.. stay their ids).

The example targets were picked by ``python -m ctrplan.collision.build_scenes`` as reachable
tip positions and numbered ``t01``..``t12``; ``scene.yaml`` keeps those ids (the scene build is
checked bit for bit). The names below say where each target lies, read from the geometry
(``tests/test_vocabulary.py`` re-measures the facts each name rests on):

- ``airway``: every target lies in the lumen of the distal trachea (1-3 mm from its wall).
  ``carina`` is the one nearest both main bronchi (summed distance); ``lower_trachea_N`` are
  within 15 mm of a main bronchus, ``mid_trachea_N`` farther up; N orders by that distance.
- ``neuro`` (MNI152, x right): ``left_frontal_horn`` lies inside the left lateral ventricle's
  frontal horn; ``midline_near_thalamostriate_vein`` lies 1.7 mm from the ventricles near the
  midline and 3.9 mm from that (procedural) vein; the others lie within 12 mm of the ventricles
  (``periventricular_left|right_N``, side by the sign of x).
- ``skull_base`` (origin at the sella): all in the sphenoid sinus; ``near_sella`` is the target
  nearest the origin; ``near_left_carotid``, ``near_right_carotid``, ``near_left_optic_nerve``
  and ``below_optic_chiasm`` are within 6.5 mm of that structure (and nearer to it than to any
  other obstacle, both optic nerves alike for the chiasm); the rest are ``sphenoid_sinus_N``.
- ``bronchial_tree`` is procedural: ``carina`` is the target nearest the first bifurcation,
  ``lower_trachea_N`` lie in the trunk above it, and ``bronchus_x_pos_N`` / ``bronchus_x_neg_N``
  in the first-generation branch toward +x / -x (the procedural frame names no side), N from
  proximal to distal.

Scenes without a table here (``design_bend``, your own scenes) keep their names as written.
"""

from __future__ import annotations

#: scene name -> {target id: anatomical name}
NAMES: dict[str, dict[str, str]] = {
    "airway": {
        "t01": "carina", "t10": "lower_trachea_1", "t11": "lower_trachea_2",
        "t04": "lower_trachea_3", "t08": "lower_trachea_4", "t09": "mid_trachea_1",
        "t03": "mid_trachea_2", "t12": "mid_trachea_3", "t06": "mid_trachea_4",
        "t05": "mid_trachea_5", "t07": "mid_trachea_6", "t02": "mid_trachea_7",
    },
    "neuro": {
        "t04": "left_frontal_horn", "t08": "midline_near_thalamostriate_vein",
        "t01": "periventricular_left_1", "t05": "periventricular_left_2",
        "t10": "periventricular_left_3", "t11": "periventricular_left_4",
        "t02": "periventricular_right_1", "t03": "periventricular_right_2",
        "t06": "periventricular_right_3", "t07": "periventricular_right_4",
        "t09": "periventricular_right_5", "t12": "periventricular_right_6",
    },
    "skull_base": {
        "t01": "near_sella", "t05": "near_left_carotid", "t04": "near_right_carotid",
        "t03": "near_left_optic_nerve", "t08": "below_optic_chiasm",
        "t06": "sphenoid_sinus_1", "t11": "sphenoid_sinus_2", "t12": "sphenoid_sinus_3",
        "t07": "sphenoid_sinus_4", "t09": "sphenoid_sinus_5", "t10": "sphenoid_sinus_6",
        "t02": "sphenoid_sinus_7",
    },
    "bronchial_tree": {
        "t07": "carina", "t02": "lower_trachea_1", "t11": "lower_trachea_2",
        "t05": "bronchus_x_pos_1", "t08": "bronchus_x_pos_2", "t04": "bronchus_x_pos_3",
        "t06": "bronchus_x_pos_4", "t01": "bronchus_x_pos_5",
        "t09": "bronchus_x_neg_1", "t12": "bronchus_x_neg_2", "t10": "bronchus_x_neg_3",
        "t03": "bronchus_x_neg_4",
    },
}


def anatomical_name(scene_name: str, target_id: str) -> str:
    """The anatomical name of a shipped scene's target id, or ``""`` where there is none."""
    return NAMES.get(scene_name, {}).get(target_id, "")
