"""The stiffness model a fit chooses from the frame pairs (softgrip_calib.select).

The decision rule is checked on hand-made records (fast); the whole selection on closures of the
independent elastic rod (synthetic.rod, its own solver), without rendering (slow): a gripper
stiffer at its base on a compliant clamp needs the richer model, a uniform clamped one does not.
"""

from __future__ import annotations

import numpy as np
import pytest

from softgrip_calib.profile import CalibrationProfile
from softgrip_calib.select import MIN_GAIN_FRACTION, MIN_GAIN_MM, STIFFNESS_MODELS, _choose, describe_selection


def records(*held_out, failures=None):
    failures = failures or [None] * len(held_out)
    return [{"model": m.name, "parameters": list(m.parameters), "residual_rms_mm": 0.1,
             "held_out_rms_mm": h, "failure": f} for m, h, f in zip(STIFFNESS_MODELS, held_out, failures)]


def test_the_models_are_nested_simplest_first() -> None:
    params = [set(m.parameters) for m in STIFFNESS_MODELS]
    assert params[0] == set() and all(a < b for a, b in zip(params, params[1:]))


def test_a_richer_model_is_chosen_only_when_it_predicts_held_out_pairs_clearly_better() -> None:
    # uniform 1.0 mm: a gain must be >= max(0.02, 0.1 * 1.0) = 0.1 mm.
    assert MIN_GAIN_MM == 0.02 and MIN_GAIN_FRACTION == 0.1
    assert _choose(records(1.0, 0.95, 0.93), 3)[0] == "uniform"  # gains 0.05, 0.07: within the noise
    assert _choose(records(1.0, 0.85, 0.84), 3)[0] == "stiffness ratio"  # 0.15, then 0.01 more
    # The third model is compared with the chosen second one (0.5 -> 0.3: 0.2 >= 0.05).
    assert _choose(records(1.0, 0.5, 0.3), 3)[0] == "stiffness ratio + base compliance"
    # ... and with uniform when the second was not better enough (1.0 -> 0.6).
    assert _choose(records(1.0, 0.95, 0.6), 3)[0] == "stiffness ratio + base compliance"
    # At small errors the absolute margin rules: 0.1 -> 0.085 is 15 % but only 0.015 mm.
    assert _choose(records(0.1, 0.085, 0.084), 3)[0] == "uniform"
    # A model that could not be judged is never chosen, and the reason says so.
    name, reason = _choose(records(1.0, None, 0.95, failures=[None, "did not converge: ...", None]), 3)
    assert name == "uniform" and "not judged (did not converge" in reason


def test_too_few_pairs_with_an_object_keep_the_uniform_finger_and_say_what_to_add() -> None:
    name, reason = _choose(records(None, None, None), 1)
    assert name == "uniform" and "Add pairs" in reason and "different heights" in reason


def test_the_selection_is_recorded_in_the_profile_and_survives_a_round_trip(tmp_path) -> None:
    from softgrip_calib.profile import FingerEntry, FitEntry, load_profile, save_profile

    selection = {"chosen": "stiffness ratio", "reason": "because", "candidates": records(0.4, 0.2, None, failures=[
        None, None, "did not converge: the least-squares fit did not converge within 100 steps"])}
    finger = FingerEntry(52.0, 0.5, 4.0, 10, stiffness_ratio=1.8)
    profile = CalibrationProfile(fingers={"left": finger, "right": finger}, base_separation=64.0, segmentation={},
                                 camera={"name": "x", "intrinsics": None},
                                 fit=FitEntry(method="least-squares", frames=["a"], residual_rms_mm=0.1,
                                              frame_residual_rms_mm=[0.1], model_selection=selection))
    save_profile(profile, tmp_path / "p.json")
    assert load_profile(tmp_path / "p.json").fit.model_selection == selection
    lines = describe_selection(selection)
    assert lines[1].lstrip().startswith("* stiffness ratio ") and "0.200 mm" in lines[1]
    assert "did not converge" in lines[2] and lines[-1].startswith("  chosen: stiffness ratio")


@pytest.mark.slow
@pytest.mark.parametrize("ratio, compliance, richer", [(2.0, 0.3, True), (1.0, 0.0, False)])
def test_rod_closures_choose_the_model_their_gripper_needs(ratio, compliance, richer) -> None:
    """Four rod closures on discs at different heights and the free closure, N = 10: a finger twice
    as stiff at its base on a clamp of compliance 0.3 is not explained by a uniform clamped one (its
    held-out error drops by more than half with the richer models), a uniform clamped one is (the
    richer models cannot predict its held-out pairs better than the model-to-rod difference)."""
    import warnings

    from softgrip_calib.fit import Observation
    from softgrip_calib.select import fit_stiffness_model
    from softgrip_jax import PolygonSDF
    from synthetic.rod import RodMechanics, free_arc_points
    from tests.calib.test_fit_mechanics import (BASES, DISCS, HANDEDNESS, LENGTH, N, TRUE_THETA, rod_observation,
                                                start_profile)

    rod = RodMechanics(stiffness_ratio=ratio, base_compliance=compliance)
    pairs = [rod_observation(disc, f"disc {i}", rod) for i, disc in enumerate(DISCS[:4])]
    free = np.stack([np.asarray(free_arc_points(b, TRUE_THETA[s], LENGTH, np.linspace(0.0, LENGTH, N + 1),
                                                HANDEDNESS[s])) for s, b in zip(("left", "right"), BASES)])
    pairs.append(Observation(PolygonSDF.regular((0.0, 300.0), 5.0, 64), BASES, free, "free", free_closure=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        profile = fit_stiffness_model(pairs, start_profile(), progress=False)
    selection = profile.fit.model_selection
    held = {c["model"]: c["held_out_rms_mm"] for c in selection["candidates"]}
    assert all(c["failure"] is None for c in selection["candidates"]), selection
    if richer:
        assert selection["chosen"] != "uniform", selection
        assert min(held["stiffness ratio"], held["stiffness ratio + base compliance"]) < 0.5 * held["uniform"]
        assert all(profile.fingers[s].stiffness_ratio > 1.3 for s in ("left", "right"))
    else:
        assert selection["chosen"] == "uniform", selection
        assert profile.fingers["left"].stiffness_ratio == 1.0 and profile.fingers["left"].base_compliance == 0.0
    # The free closure keeps Theta: within 0.01 rad of the truth whatever the model.
    for side in ("left", "right"):
        assert abs(profile.fingers[side].theta_entire - TRUE_THETA[side]) < 0.01
