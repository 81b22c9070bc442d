"""Least-squares calibration through the mechanics estimate: the stiffness parameters.

The observations are closures of the independent elastic rod (synthetic.rod, 96 segments,
its own solver) against polygon objects, without rendering: the fit has to find a gripper whose
bending stiffness doubles from tip to base. All mechanics fits here use 64-vertex PolygonSDFs,
N = 10 and at most 16 frame pairs, so they share one compilation of the fit (most of the time).
"""

from __future__ import annotations

import numpy as np
import pytest

from softgrip_calib.fit import COMPLIANCE_START, PARAMETERS, FitError, Observation, fit
from softgrip_calib.profile import CalibrationProfile, FingerEntry, FitEntry
from softgrip_jax import PolygonSDF
from synthetic.rod import RodMechanics, close_rod, free_arc_points, observed_joints
from softgrip_jax import Geometric, Mechanics

N = 10
LENGTH, HALF_THICKNESS, SEPARATION = 52.0, 4.0, 64.0
TRUE_THETA = {"left": 0.55, "right": 0.45}
TRUE_RATIO = 2.0  # base twice as stiff as the tip
BASES = np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
HANDEDNESS = {"left": 1.0, "right": -1.0}
#: Discs ((x, y) mm, radius mm) between the fingers, clear of the open fingers (|x| + radius < 28)
#: and wrapped by both closing fingers, at different heights: contacts at different places along
#: the fingers, which is what separates the stiffness profile from Theta.
DISCS = [((0.0, 36.0), 10.0), ((3.0, 30.0), 12.0), ((-4.0, 42.0), 9.0), ((1.0, 24.0), 14.0),
         ((-2.0, 33.0), 11.0), ((2.0, 44.0), 8.0)]


def start_profile(theta: float = 0.5, ratio: float = 1.0) -> CalibrationProfile:
    finger = FingerEntry(LENGTH, theta, HALF_THICKNESS, N, stiffness_ratio=ratio)
    return CalibrationProfile(fingers={"left": finger, "right": finger}, base_separation=SEPARATION,
                              segmentation={}, camera={"name": "synthetic", "intrinsics": None},
                              fit=FitEntry(method="one-frame", frames=["nominal"]))


def rod_observation(disc, label: str, mechanics: RodMechanics) -> Observation:
    """Both fingers closed by the rod on a disc, observed at N equal arc lengths (mm)."""
    sdf = PolygonSDF.regular(*disc, 64)
    observed = []
    for side, base in zip(("left", "right"), BASES):
        closure = close_rod(base, TRUE_THETA[side], LENGTH, HALF_THICKNESS, sdf, mechanics=mechanics,
                            handedness=HANDEDNESS[side])
        assert bool(closure.converged), (label, side)
        observed.append(np.asarray(observed_joints(closure, N), np.float64))
    return Observation(sdf, BASES, np.stack(observed), label)


def test_the_stiffness_parameters_are_registered_with_their_transforms() -> None:
    assert PARAMETERS["stiffness_ratio"].transform == "log"
    assert PARAMETERS["base_compliance"].transform == "sqrt"
    for name in ("stiffness_ratio", "base_compliance"):
        assert PARAMETERS[name].methods == ("mechanics",) and PARAMETERS[name].min_frames == 2
    assert 0.0 < COMPLIANCE_START < 0.1


@pytest.mark.parametrize("parameters", [("theta_entire", "stiffness_ratio"), ("base_compliance",)])
def test_stiffness_parameters_need_the_mechanics_estimate(parameters) -> None:
    free = np.stack([np.asarray(free_arc_points(b, TRUE_THETA[s], LENGTH, np.linspace(0.0, LENGTH, N + 1),
                                                HANDEDNESS[s])) for s, b in zip(("left", "right"), BASES)])
    pairs = [Observation(PolygonSDF.regular((0.0, 300.0), 5.0, 64), BASES, free, f"pair {i}") for i in range(3)]
    with pytest.raises(FitError, match=r"only affect\(s\) the mechanics estimate, so 'geometric' cannot fit "
                                       r"them: fit with estimator=Mechanics\(\) \(softgrip calibrate --fit \.\.\. "
                                       r"--method mechanics\)"):
        fit(pairs, start_profile(), parameters, estimator=Geometric(), progress=False)
    with pytest.raises(FitError, match="estimator must be a softgrip_jax estimator"):
        fit(pairs, start_profile(), ["theta_entire"], estimator="spring", progress=False)
    with pytest.raises(FitError, match=r"pass the estimator itself, Mechanics\(\)"):
        fit(pairs, start_profile(), ["theta_entire"], estimator="mechanics", progress=False)


@pytest.mark.slow
def test_a_stiffness_doubling_toward_the_base_is_recovered_from_rod_closures() -> None:
    """The issue's key test: fit Theta and the base-to-tip stiffness ratio of both fingers, from a
    uniform start (ratio 1.0, Theta 0.5 rad), to six rod closures of a finger twice as stiff at the
    base as at the tip.

    Tolerance: the observations carry no noise, so what remains is the model difference between a
    10-link spring chain and the 96-segment rod (residual RMS about 0.01 mm). The ratio must be
    within 0.1 of 2.0 (5 %: an order of magnitude finer than the 1.0 -> 2.0 change the fit has to
    find) and within three of its own standard errors (so the reported errors are honest), and Theta
    within 0.002 rad (a tenth of a millimetre of tip position over L = 52 mm).
    """
    observations = [rod_observation(disc, f"disc {i}", RodMechanics(stiffness_ratio=TRUE_RATIO))
                    for i, disc in enumerate(DISCS)]
    fitted = fit(observations, start_profile(), ("theta_entire", "stiffness_ratio"), estimator=Mechanics(),
                 progress=False)
    errors = fitted.fit.standard_errors
    for side in ("left", "right"):
        finger = fitted.fingers[side]
        se = errors[f"{side}.stiffness_ratio"]
        assert abs(finger.stiffness_ratio - TRUE_RATIO) < 0.1, (side, finger.stiffness_ratio, se)
        assert abs(finger.stiffness_ratio - TRUE_RATIO) < 3 * se, (side, finger.stiffness_ratio, se)
        assert abs(finger.theta_entire - TRUE_THETA[side]) < 0.002, (side, finger.theta_entire)
        assert 0.0 < errors[f"{side}.theta_entire"] < 0.002
        assert finger.base_compliance == 0.0  # not fitted: kept from the start
    assert fitted.fit.method == "least-squares" and fitted.fit.estimate_method == "mechanics"
    assert fitted.fit.skipped == [] and fitted.fit.frames == [o.label for o in observations]
    assert fitted.fit.residual_rms_mm < 0.05

    # Closures that touch nothing do not depend on the stiffness: the fit says so instead of
    # reporting an arbitrary ratio (same polygon size: the compiled fit is reused).
    free = np.stack([np.asarray(free_arc_points(b, TRUE_THETA[s], LENGTH, np.linspace(0.0, LENGTH, N + 1),
                                                HANDEDNESS[s])) for s, b in zip(("left", "right"), BASES)])
    far = [Observation(PolygonSDF.regular((0.0, 300.0), 5.0, 64), BASES, free, f"far {i}") for i in range(2)]
    with pytest.raises(FitError, match=r"do not constrain left\.stiffness_ratio, right\.stiffness_ratio.*touches an "
                                       r"object"):
        fit(far, start_profile(), ("theta_entire", "stiffness_ratio"), estimator=Mechanics(), progress=False)
