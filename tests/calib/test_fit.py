"""One-frame calibration (eqs. 4-5), the multi-frame least-squares fit, and ``softgrip calibrate``.

Every fit here but one uses 480 x 640 signed-distance grids, N = 10, the geometric estimate and at
most 16 frame pairs, so they compile the fit once (about half a minute on two cores). The one other
(marked slow) fits the sample frames in data/ through the mechanics estimate, N = 20.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_calib.fit import (FRAME_BUCKET, MIN_CLUSTERED_FRAMES, FitError, Observation, PoorlyDeterminedWarning,
                       SkippedFrameWarning, _robust, _solve, _warn_if_poorly_determined, fit, free_closure_observation,
                       load_observations, observations_from_frames)
from softgrip_calib.one_frame import free_closure_joints, one_frame_from_frames, one_frame_profile
from softgrip_calib.profile import CalibrationProfile, FingerEntry, FitEntry, load_profile
from softgrip_cli import cmd_calibrate
from softgrip_jax import DEFAULT_METHOD, FAR_MM, SDFGrid, SoftgripError
from softgrip_vision.frames import save_frame
from softgrip_vision.geometry import PlaneCamera
from synthetic.render import Scene, d405_intrinsics, render
from synthetic.rod import free_arc_points
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import shape
from softgrip_jax import Geometric, Mechanics

N = 10
LENGTH, HALF_THICKNESS, SEPARATION = 52.0, 4.0, 64.0
TRUE = {"left": 0.55, "right": 0.45}
CAMERA = PlaneCamera(d405_intrinsics(), 120.0)  # the grid of a 640 x 480 frame 120 mm away


def entry(theta: float, offset=(0.0, 0.0)) -> FingerEntry:
    return FingerEntry(LENGTH, theta, HALF_THICKNESS, N, tuple(offset))


def start_profile(left: float, right: float) -> CalibrationProfile:
    return CalibrationProfile(fingers={"left": entry(left), "right": entry(right)}, base_separation=SEPARATION,
                              segmentation={}, camera={"name": "synthetic", "intrinsics": None},
                              fit=FitEntry(method="one-frame", frames=["nominal"]))


def grid(disc=None) -> SDFGrid:
    """A frame-sized signed-distance grid: of a disc ((x, y), radius) in mm, or far everywhere."""
    h, w = CAMERA.intrinsics.height, CAMERA.intrinsics.width
    if disc is None:
        values = np.full((h, w), FAR_MM)
    else:
        (cx, cy), radius = disc
        x, y = CAMERA.px_to_mm(np.stack(np.meshgrid(np.arange(w), np.arange(h)), axis=-1)).transpose(2, 0, 1)
        values = np.hypot(x - cx, y - cy) - radius
    return SDFGrid(jnp.asarray(values, jnp.float32), jnp.asarray(CAMERA.origin_mm, jnp.float32),
                   jnp.asarray(CAMERA.spacing_mm, jnp.float32))


EMPTY = grid()


def observation(rng, label: str, noise: float = 0.2, thetas=TRUE, observed_shift=(0.0, 0.0),
                base_bias=((0.0, 0.0), (0.0, 0.0))) -> Observation:
    """A pair without an object: the closed fingers are the PCC shapes of ``thetas`` (plus Gaussian
    noise, mm) and the open frame's bases are the true ones plus ``base_bias``."""
    centre = np.array([rng.uniform(-15.0, 15.0), rng.uniform(-45.0, -35.0)])
    bases = centre + np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
    observed = np.stack([free_closure_joints(entry(thetas[side]), base, side)
                         for side, base in zip(("left", "right"), bases)])
    observed = observed + noise * rng.normal(size=observed.shape) + np.asarray(observed_shift)
    return Observation(EMPTY, bases + np.asarray(base_bias), observed, label)


def thetas(profile: CalibrationProfile) -> np.ndarray:
    return np.array([profile.fingers[side].theta_entire for side in ("left", "right")])


def quiet_fit(*args, estimator=Geometric(), **kwargs) -> CalibrationProfile:
    """The paper's geometric fit unless ``estimator`` says otherwise, without a progress bar."""
    return fit(*args, progress=False, estimator=estimator, **kwargs)


# ---------------------------------------------------------------------------------------------
# The fit at the millimetre level


@pytest.fixture(scope="module")
def five_frame_fit():
    rng = np.random.default_rng(0)
    observations = [observation(rng, f"pair {i}") for i in range(5)]
    start = start_profile(TRUE["left"] + 0.2, TRUE["right"] - 0.2)
    return observations, quiet_fit(observations, start)


def test_theta_is_recovered_from_five_noisy_frames(five_frame_fit) -> None:
    observations, fitted = five_frame_fit
    np.testing.assert_allclose(thetas(fitted), [TRUE["left"], TRUE["right"]], atol=0.005)
    assert fitted.fit.method == "least-squares" and fitted.fit.estimate_method == "geometric"
    assert fitted.fit.frames == [o.label for o in observations]
    assert fitted.fit.skipped == []
    # Noise of 0.2 mm per coordinate is 0.28 mm per joint.
    assert 0.2 < fitted.fit.residual_rms_mm < 0.36
    assert len(fitted.fit.frame_residual_rms_mm) == 5
    assert fitted.fingers["left"].length == LENGTH and fitted.fingers["left"].base_offset == (0.0, 0.0)
    assert set(fitted.fit.standard_errors) == {"left.theta_entire", "right.theta_entire"}


def test_standard_error_matches_the_analytic_value(five_frame_fit) -> None:
    """For noise sigma on every coordinate, SE(Theta) = sigma / sqrt(sum |dP_j / dTheta|^2)."""
    observations, fitted = five_frame_fit
    step = 1e-4
    for side, k in (("left", 0), ("right", 1)):
        sensitivity = 0.0
        for obs in observations:
            up = free_closure_joints(entry(TRUE[side] + step), obs.bases[k], side)
            down = free_closure_joints(entry(TRUE[side] - step), obs.bases[k], side)
            sensitivity += np.sum(((up - down) / (2 * step)) ** 2)
        analytic = 0.2 / math.sqrt(sensitivity)
        se = fitted.fit.standard_errors[f"{side}.theta_entire"]
        assert analytic / 1.5 < se < 1.5 * analytic, (side, se, analytic)


def test_standard_error_matches_the_spread_of_repeated_fits() -> None:
    rng = np.random.default_rng(7)
    start = start_profile(0.5, 0.5)
    fits = [quiet_fit([observation(rng, f"pair {i}", noise=0.5) for i in range(2)], start) for _ in range(12)]
    errors = np.array([thetas(f) for f in fits]) - [TRUE["left"], TRUE["right"]]
    reported = np.array([[f.fit.standard_errors[f"{s}.theta_entire"] for s in ("left", "right")] for f in fits])
    # Both fingers' fits are independent draws: 24 errors against their reported standard errors.
    ratio = np.sqrt(np.mean(errors**2)) / np.sqrt(np.mean(reported**2))
    assert 1 / 1.5 < ratio < 1.5, ratio


def test_standard_error_allows_for_errors_a_frame_shares() -> None:
    """Every joint of a frame shifted by the same random offset (sigma 0.3 mm per coordinate, as a
    wrong base point or plane does), plus 0.01 mm of independent noise. By hand, the fitted Theta is
    the linear projection of the shifts: SE = sigma sqrt(sum_f |g_f|^2) / S with g_f the sum over
    frame f's joints of dP/dTheta (a 2-vector) and S = sum over all joints of |dP/dTheta|^2. The
    textbook estimate, which counts each joint as an independent measurement, is several times
    smaller; the reported one must match the hand value."""
    rng = np.random.default_rng(11)
    sigma, frames = 0.3, MIN_CLUSTERED_FRAMES + 2
    observations = [observation(rng, f"pair {i}", noise=0.01, observed_shift=rng.normal(0.0, sigma, 2))
                    for i in range(frames)]
    fitted = quiet_fit(observations, start_profile(0.5, 0.5))
    step = 1e-4
    for side, k in (("left", 0), ("right", 1)):
        g2, s = 0.0, 0.0
        for obs in observations:
            up = free_closure_joints(entry(TRUE[side] + step), obs.bases[k], side)
            down = free_closure_joints(entry(TRUE[side] - step), obs.bases[k], side)
            d = (up - down) / (2 * step)  # (N+1, 2) mm / rad
            g2 += np.sum(d.sum(axis=0) ** 2)
            s += np.sum(d**2)
        by_hand = sigma * math.sqrt(g2) / s
        textbook = fitted.fit.residual_rms_mm / math.sqrt(2.0) / math.sqrt(s)
        se = fitted.fit.standard_errors[f"{side}.theta_entire"]
        assert textbook < by_hand / 2.5, (side, textbook, by_hand)
        assert by_hand / 1.6 < se < 1.6 * by_hand, (side, se, by_hand, textbook)


def test_a_stiffness_whose_effect_is_below_the_residuals_is_reported_poorly_determined() -> None:
    """Jacobian columns (mm per unit) of two joints: the ratio 2.0 moves them by 0.03 mm per 10 %,
    the residuals are 0.1 mm: warned, naming the parameter and both figures; at 0.2 mm per 10 %
    it is not; Theta is never judged this way."""
    residuals = np.full((3, 2, 2, 2), 0.1 / math.sqrt(2.0))  # (F, 2, J, 2), each joint 0.1 mm away
    weak = np.array([[0.15, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 0.1, 5.0], [0.0, 0.0, 5.0]])  # (M, P)
    columns = [("left", "stiffness_ratio"), ("left", "stiffness_ratio"), ("left", "theta_entire")]
    values = {("left", "stiffness_ratio"): [2.0], ("left", "theta_entire"): [0.5]}
    with pytest.warns(PoorlyDeterminedWarning, match=r"left\.stiffness_ratio = 2\.000 is poorly determined.*10 % "
                                                     r"moves no joint by more than 0\.030 mm, less than the residual "
                                                     r"RMS 0\.100 mm"):
        _warn_if_poorly_determined(weak[:, [0, 2]], [columns[0], columns[2]], values, residuals)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_if_poorly_determined(weak[:, [0, 2]] * [[1.0 / 0.15, 1.0]], [columns[0], columns[2]], values, residuals)


def test_one_grossly_wrong_frame_among_ten_moves_theta_little() -> None:
    rng = np.random.default_rng(1)
    good = [observation(rng, f"pair {i}") for i in range(9)]
    bad = observation(rng, "shifted pair", observed_shift=(10.0, 0.0))  # e.g. a wrong mask
    start = start_profile(0.5, 0.5)
    clean = thetas(quiet_fit(good, start))
    robust = thetas(quiet_fit([*good[:4], bad, *good[4:]], start))
    assert np.abs(robust - clean).max() < 0.01, (robust, clean)
    # Without the robust loss (an enormous scale is plain least squares) the same frame drags Theta.
    plain = thetas(quiet_fit([*good[:4], bad, *good[4:]], start, loss_scale_mm=1e6))
    assert np.abs(plain - clean).max() > 0.01, (plain, clean)


def test_one_frame_with_a_wrong_object_mask_among_ten_moves_theta_little() -> None:
    """A segmentation that saw an object where there was none: that frame's estimate wraps a disc
    the real finger never met, so its residuals are millimetres; the robust loss must contain it."""
    rng = np.random.default_rng(2)
    good = [observation(rng, f"pair {i}") for i in range(9)]
    wrong = observation(rng, "wrong mask")
    centre = wrong.bases.mean(axis=0)
    wrong = Observation(grid(((centre[0], centre[1] + 30.0), 12.0)), wrong.bases, wrong.observed, wrong.label)
    start = start_profile(0.5, 0.5)
    clean = thetas(quiet_fit(good, start))
    robust = thetas(quiet_fit([*good[:4], wrong, *good[4:]], start))
    assert np.abs(robust - clean).max() < 0.01, (robust, clean)
    # The wrong frame does pull: plain least squares moves Theta further.
    plain = thetas(quiet_fit([*good[:4], wrong, *good[4:]], start, loss_scale_mm=1e6))
    assert np.abs(plain - clean).max() > np.abs(robust - clean).max(), (plain, robust, clean)


def test_base_offsets_and_theta_are_fitted_together() -> None:
    rng = np.random.default_rng(2)
    bias = ((0.8, -1.2), (-0.6, -1.0))  # the open frames' bases are seen off by this
    observations = [observation(rng, f"pair {i}", base_bias=bias) for i in range(6)]
    fitted = quiet_fit(observations, start_profile(0.4, 0.6), ["theta_entire", "base_offset"])
    np.testing.assert_allclose(thetas(fitted), [TRUE["left"], TRUE["right"]], atol=0.005)
    for side, offset in zip(("left", "right"), bias):
        np.testing.assert_allclose(fitted.fingers[side].base_offset, -np.asarray(offset), atol=0.2)
        se = fitted.fit.standard_errors[f"{side}.base_offset"]
        assert len(se) == 2 and all(0.0 < v < 0.2 for v in se)


def test_robust_residuals_square_to_twice_the_loss() -> None:
    r = jnp.array([[0.0, 0.0], [0.03, -0.04], [3.0, 4.0], [-30.0, 40.0]])
    e = jnp.linalg.norm(r, axis=-1)
    huber = jnp.where(e <= 1.0, 0.5 * e**2, e - 0.5)
    cauchy = 0.5 * jnp.log1p(e**2)
    for loss, rho in (("huber", huber), ("cauchy", cauchy)):
        robust = jax.jit(lambda x, loss=loss: _robust(x, jnp.asarray(1.0), loss))
        out = robust(r)
        np.testing.assert_allclose(jnp.sum(out**2, axis=-1), 2.0 * rho, rtol=1e-5)
        np.testing.assert_allclose(out[:2], r[:2], rtol=0.05)  # small residuals unchanged
        grad = jax.jit(jax.jacfwd(robust))(r[:1])
        assert np.isfinite(np.asarray(grad)).all()  # no NaN at a zero residual


# ---------------------------------------------------------------------------------------------
# Frames that cannot be used, and bad input


def test_a_non_finite_frame_is_skipped_with_a_warning() -> None:
    rng = np.random.default_rng(3)
    observations = [observation(rng, f"pair {i}") for i in range(4)]
    broken = observation(rng, "broken pair")
    broken.observed[0, 3] = np.nan
    with pytest.warns(SkippedFrameWarning, match="broken pair: skipped: non-finite observed joints of the left"):
        fitted = quiet_fit([*observations, broken], start_profile(0.5, 0.5))
    assert fitted.fit.frames == [o.label for o in observations]
    assert fitted.fit.skipped == [{"frame": "broken pair", "reason": "non-finite observed joints of the left finger"}]
    np.testing.assert_allclose(thetas(fitted), [TRUE["left"], TRUE["right"]], atol=0.01)


def test_a_frame_whose_open_finger_overlaps_the_object_is_skipped() -> None:
    rng = np.random.default_rng(4)
    observations = [observation(rng, f"pair {i}") for i in range(3)]
    clash = observation(rng, "clash")
    clash = Observation(grid((clash.bases[0] + (0.0, 20.0), 6.0)), clash.bases, clash.observed, "clash")
    with pytest.warns(SkippedFrameWarning, match="clash: skipped: .*invalid: left finger INITIAL_OVERLAP"):
        fitted = quiet_fit([*observations, clash], start_profile(0.5, 0.5))
    assert [s["frame"] for s in fitted.fit.skipped] == ["clash"]
    assert len(fitted.fit.frames) == 3


def test_no_usable_frame() -> None:
    with pytest.raises(FitError, match=r"no usable frame pair \(of 0\): none given"):
        quiet_fit([], start_profile(0.5, 0.5))
    rng = np.random.default_rng(5)
    broken = [observation(rng, f"pair {i}") for i in range(2)]
    for obs in broken:
        obs.bases[1, 0] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedFrameWarning)
        with pytest.raises(FitError, match=r"no usable frame pair \(of 3\): earlier: no gripper; pair 0: non-finite "
                                           r"finger bases of the right finger; pair 1: non-finite"):
            quiet_fit(broken, start_profile(0.5, 0.5), skipped=[{"frame": "earlier", "reason": "no gripper"}])


def test_a_single_frame_cannot_determine_a_base_offset() -> None:
    rng = np.random.default_rng(6)
    single = [observation(rng, "only pair")]
    with pytest.raises(FitError, match=r"a fit of left\.base_offset, right\.base_offset from 1 usable frame pair\(s\) "
                                       r"is under-determined: it needs at least 2"):
        quiet_fit(single, start_profile(0.5, 0.5), ["theta_entire", "base_offset"])
    # Theta alone is determined by one pair (this is what the one-frame calibration does).
    fitted = quiet_fit(single, start_profile(0.5, 0.5))
    np.testing.assert_allclose(thetas(fitted), [TRUE["left"], TRUE["right"]], atol=0.01)


@pytest.mark.parametrize("kwargs, message", [
    ({"parameters": ["stiffness"]}, "unknown parameter.*'stiffness'.*theta_entire, base_offset"),
    ({"parameters": []}, "unknown parameter.*none given"),
    ({"loss": "l1"}, "loss must be 'huber' or 'cauchy'"),
    ({"loss_scale_mm": 0.0}, "loss_scale_mm must be a finite number of mm > 0"),
    ({"max_steps": 0}, "max_steps must be an integer >= 1"),
])
def test_bad_settings(kwargs, message) -> None:
    rng = np.random.default_rng(8)
    with pytest.raises(FitError, match=message):
        quiet_fit([observation(rng, "pair")], start_profile(0.5, 0.5), **kwargs)


def test_observations_must_match_the_profile() -> None:
    rng = np.random.default_rng(9)
    obs = observation(rng, "pair")
    with pytest.raises(FitError, match="pair: 11 observed joints per finger, but the start profile has n_links = 20"):
        quiet_fit([obs], CalibrationProfile(
            fingers={s: FingerEntry(LENGTH, 0.5, HALF_THICKNESS, 20) for s in ("left", "right")},
            base_separation=SEPARATION, segmentation={}, camera={"name": "x", "intrinsics": None},
            fit=FitEntry("one-frame", ["x"])))
    with pytest.raises(FitError, match="same n_links"):
        quiet_fit([obs], CalibrationProfile(
            fingers={"left": entry(0.5), "right": FingerEntry(LENGTH, 0.5, HALF_THICKNESS, 12)},
            base_separation=SEPARATION, segmentation={}, camera={"name": "x", "intrinsics": None},
            fit=FitEntry("one-frame", ["x"])))
    with pytest.raises(FitError, match=r"bad: bases must be \(2, 2\)"):
        Observation(EMPTY, np.zeros(2), obs.observed, "bad")
    with pytest.raises(FitError, match=r"bad: observed must be \(2, N\+1, 2\)"):
        Observation(EMPTY, obs.bases, obs.observed[0], "bad")
    with pytest.raises(FitError, match="bad: sdf must be a softgrip_jax SDF"):
        Observation(np.zeros((4, 4)), obs.bases, obs.observed, "bad")


def test_fits_of_other_frame_counts_and_parameters_reuse_the_compilation(five_frame_fit) -> None:
    rng = np.random.default_rng(10)
    compiled = _solve._cache_size()
    quiet_fit([observation(rng, f"pair {i}") for i in range(FRAME_BUCKET - 3)], start_profile(0.5, 0.5),
              ["theta_entire", "base_offset"])
    quiet_fit([observation(rng, f"pair {i}") for i in range(3)], start_profile(0.6, 0.4))
    assert _solve._cache_size() == compiled


# ---------------------------------------------------------------------------------------------
# One-frame calibration (eqs. 4-5) on keypoints


@dataclass(frozen=True)
class Keypoints:
    """The keypoints the one-frame calibration reads, as softgrip_vision.keypoints.FingerKeypoints has them."""

    base_mm: np.ndarray
    tip_mm: np.ndarray
    half_thickness_mm: float
    joints: np.ndarray

    @property
    def length_mm(self) -> float:
        return float(np.hypot(*(self.tip_mm - self.base_mm)))

    @property
    def arc_length_mm(self) -> float:
        return float(np.hypot(*np.diff(self.joints, axis=0).T).sum())

    def observed_mm(self, n_links: int) -> np.ndarray:
        assert n_links == len(self.joints) - 1
        return self.joints


def keypoints(base, theta: float, side: str, half_thickness: float = HALF_THICKNESS) -> Keypoints:
    joints = free_closure_joints(entry(theta), np.asarray(base, np.float64), side)
    return Keypoints(joints[0], joints[-1], half_thickness, joints)


def test_one_frame_calibration_by_eqs_4_and_5() -> None:
    closed = [keypoints((-30.0, -40.0), 0.6, "left"), keypoints((30.0, -40.0), 0.4, "right")]
    opened = [keypoints((-31.0, -41.0), 0.0, "left", 3.8), keypoints((31.5, -41.0), 0.0, "right", 4.2)]
    profile = one_frame_profile(closed, opened, N, label="open + closed")
    left, right = profile.fingers["left"], profile.fingers["right"]
    tip = closed[0].tip_mm - closed[0].base_mm
    assert left.theta_entire == pytest.approx(math.atan(tip[0] / tip[1]))  # eq. 4
    assert left.theta_entire == pytest.approx(0.6, abs=1e-5)
    assert right.theta_entire == pytest.approx(0.4, abs=1e-5)  # mirrored: curls toward -x
    assert left.length == pytest.approx(LENGTH, rel=1e-5)  # eq. 5: the open finger's base-tip distance
    assert (left.half_thickness, right.half_thickness) == (3.8, 4.2)
    assert profile.base_separation == pytest.approx(62.5)
    assert profile.fit.method == "one-frame" and profile.fit.frames == ["open + closed"]
    assert profile.fit.residual_rms_mm < 1e-3  # a PCC closure is fitted exactly


def test_one_frame_residual_measures_how_far_the_closure_is_from_one_curvature() -> None:
    closed = [keypoints((-30.0, -40.0), 0.6, "left"), keypoints((30.0, -40.0), 0.4, "right")]
    bent = Keypoints(closed[0].base_mm, closed[0].tip_mm, HALF_THICKNESS,
                     closed[0].joints + np.array([1.0, 0.0]) * np.sin(np.linspace(0, np.pi, N + 1))[:, None])
    opened = [keypoints((-30.0, -40.0), 0.0, "left"), keypoints((30.0, -40.0), 0.0, "right")]
    profile = one_frame_profile([bent, closed[1]], opened, N)
    assert 0.3 < profile.fit.residual_rms_mm < 1.0


def test_one_frame_refuses_a_finger_bent_outward() -> None:
    closed = [keypoints((-30.0, -40.0), 0.5, "right"), keypoints((30.0, -40.0), 0.5, "left")]  # sides swapped
    opened = [keypoints((-30.0, -40.0), 0.0, "left"), keypoints((30.0, -40.0), 0.0, "right")]
    with pytest.raises(SoftgripError, match="left finger of the closed frame bends away"):
        one_frame_profile(closed, opened, N)


# ---------------------------------------------------------------------------------------------
# Rendered frames: the whole pipeline, and the command


def closed_centrelines(center, thetas_=TRUE):
    shapes = {side: np.asarray(free_arc_points((0.0, 0.0), thetas_[side], LENGTH, np.linspace(0.0, LENGTH, 257)))
              for side in ("left", "right")}
    return gripper_centrelines(center, SEPARATION, LENGTH, left_shape=shapes["left"], right_shape=shapes["right"])


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Frame folders: a calibration pair (closed without object, open) and four fit pairs (open frames
    with an object out of reach or none; closed along the free arcs), plus a pair whose closed frame
    shows no gripper."""
    root = tmp_path_factory.mktemp("frames")
    intrinsics = d405_intrinsics()

    def write(name, scene):
        return save_frame(render(scene, intrinsics), root / name)

    out = {"closed": write("closed", Scene(closed_centrelines((0.0, -40.0)), seed=1)),
           "open": write("open", Scene(gripper_centrelines((0.0, -40.0), SEPARATION, LENGTH), seed=2)),
           "pairs": []}
    for i, (cx, cy) in enumerate([(-8.0, -42.0), (5.0, -38.0), (10.0, -44.0), (-3.0, -36.0)]):
        polygon = shape(("circle", "square", "clover", None)[i] or "circle", 24.0) + (cx + 2.0, cy + 80.0)
        open_scene = Scene(gripper_centrelines((cx, cy), SEPARATION, LENGTH),
                           object_polygon=polygon if i < 3 else None, seed=10 + i)
        out["pairs"].append((write(f"open_{i}", open_scene),
                             write(f"closed_{i}", Scene(closed_centrelines((cx, cy)), seed=20 + i))))
    out["pairs"].append((out["pairs"][0][0], write("closed_empty", Scene([], seed=30))))
    return out


def test_one_frame_calibration_from_rendered_frames(frames) -> None:
    from softgrip_vision.frames import load_frame

    profile = one_frame_from_frames(load_frame(frames["closed"]), load_frame(frames["open"]), N,
                                    camera_name="synthetic")
    np.testing.assert_allclose(thetas(profile), [TRUE["left"], TRUE["right"]], atol=0.01)
    for side in ("left", "right"):
        assert profile.fingers[side].length == pytest.approx(LENGTH, rel=0.01)
        assert profile.fingers[side].half_thickness == pytest.approx(HALF_THICKNESS, abs=0.3)
    assert profile.base_separation == pytest.approx(SEPARATION, abs=0.5)
    assert profile.fit.residual_rms_mm < 0.5
    assert profile.camera["name"] == "synthetic" and profile.camera["intrinsics"]["fx"] == d405_intrinsics().fx


def test_least_squares_fit_on_rendered_frames(frames) -> None:
    from softgrip_vision.frames import load_frame

    with pytest.warns(SkippedFrameWarning, match="closed_empty: skipped: .*gripper"):
        observations, skipped = load_observations(frames["pairs"], None, N, progress=False)
    assert len(observations) == 4 and len(skipped) == 1
    assert isinstance(observations[0].sdf, SDFGrid) and observations[0].observed.shape == (2, N + 1, 2)
    assert not any(o.free_closure for o in observations)
    calibration = free_closure_observation(load_frame(frames["open"]), load_frame(frames["closed"]), None, N,
                                           "calibration pair")
    assert calibration.free_closure and calibration.observed.shape == (2, N + 1, 2)
    fitted = quiet_fit([*observations, calibration], start_profile(0.5, 0.5), skipped=skipped)
    np.testing.assert_allclose(thetas(fitted), [TRUE["left"], TRUE["right"]], atol=0.01)
    assert fitted.fit.residual_rms_mm < 0.6
    assert [s["frame"] for s in fitted.fit.skipped] == [skipped[0]["frame"]]
    # The per-frame report: every used pair, the free-closure pair named.
    report = fitted.fit
    assert report.frames == [*(o.label for o in observations), "calibration pair"]
    assert report.free_closure == "calibration pair"
    for values in (report.frame_residual_rms_mm, report.frame_start_residual_rms_mm, report.frame_mid_error_mm,
                   report.frame_tip_error_mm):
        assert len(values) == 5 and all(0.0 <= v < 5.0 for v in values)
    # Theta 0.5 at the start, the true 0.55 / 0.45 fitted: every pair's residual drops.
    assert all(fitted_ < start for fitted_, start in zip(report.frame_residual_rms_mm,
                                                        report.frame_start_residual_rms_mm))


def test_at_most_one_free_closure_pair() -> None:
    rng = np.random.default_rng(11)
    pairs = [dataclasses.replace(observation(rng, f"pair {i}"), free_closure=True) for i in range(2)]
    with pytest.raises(FitError, match=r"2 frame pairs are marked as the free closure \(pair 0; pair 1\)"):
        quiet_fit(pairs, start_profile(0.5, 0.5))


def test_a_free_closure_pair_whose_closed_frame_shows_an_object_is_refused() -> None:
    from softgrip_vision.frames import load_frame

    with pytest.raises(SoftgripError, match=r"^square_closed shows an object \(\d+ px\): the free-closure pair needs"):
        free_closure_observation(load_frame(DATA / "square_open"), load_frame(DATA / "square_closed"), None, 20,
                                 closed_name="square_closed")


# ---------------------------------------------------------------------------------------------
# The sample frames in data/: a fit over the pairs with objects, with and without the calibration pair


DATA = Path(__file__).resolve().parents[2] / "data"
SCENES = ("circle", "square", "star_a")


@pytest.fixture(scope="module")
def sample_fits():
    """Through the mechanics estimate (the default), from the one-frame calibration of the sample
    calibration pair (N = 20): the fit over the three object pairs with the calibration pair, and
    without it (its free-closure residual at the objects-only values read as the start residual of
    a fit from them)."""
    from softgrip_vision.frames import load_frame

    start = one_frame_from_frames(load_frame(DATA / "calib_closed"), load_frame(DATA / "calib_open"), 20,
                                  label="calib_open + calib_closed")
    objects, skipped = load_observations([(DATA / f"{s}_open", DATA / f"{s}_closed") for s in SCENES], None, 20,
                                         progress=False)
    assert not skipped
    calibration = free_closure_observation(load_frame(DATA / "calib_open"), load_frame(DATA / "calib_closed"), None,
                                           20, "calib_open + calib_closed")
    with_pair = fit([*objects, calibration], start, estimator=Mechanics(), progress=False)
    objects_only = fit(objects, start, estimator=Mechanics(), progress=False)
    from_objects_only = fit([*objects, calibration], objects_only, estimator=Mechanics(), progress=False)
    return start, with_pair, objects_only, from_objects_only


@pytest.mark.slow
def test_the_calibration_pair_keeps_the_free_closure(sample_fits) -> None:
    start, with_pair, _, _ = sample_fits
    report = with_pair.fit
    assert report.frames[-1] == report.free_closure == "calib_open + calib_closed"
    one_frame, fitted = report.frame_start_residual_rms_mm[-1], report.frame_residual_rms_mm[-1]
    # The start is the one-frame calibration: its residual is the one-frame calibration's (here through
    # the estimate and the open frame's bases, not eq. 4's own comparison, so not exactly equal).
    assert one_frame == pytest.approx(start.fit.residual_rms_mm, abs=0.05)
    assert fitted <= one_frame + 0.1, (fitted, one_frame)
    for values in (report.frame_residual_rms_mm, report.frame_start_residual_rms_mm, report.frame_mid_error_mm,
                   report.frame_tip_error_mm):
        assert len(values) == 4 and all(0.0 <= v < 1.0 for v in values)
    np.testing.assert_allclose(thetas(with_pair), 0.55, atol=0.005)


@pytest.mark.slow
def test_without_the_calibration_pair_the_objects_bend_theta(sample_fits) -> None:
    """What the calibration pair prevents: fitted to the object pairs alone, Theta moves so that the
    free closure's residual grows (on these frames from 0.07 mm at the one-frame calibration to
    0.26 mm)."""
    start, with_pair, objects_only, from_objects_only = sample_fits
    assert objects_only.fit.free_closure is None and len(objects_only.fit.frames) == 3
    free_at_objects_only = from_objects_only.fit.frame_start_residual_rms_mm[-1]
    assert free_at_objects_only > with_pair.fit.frame_residual_rms_mm[-1]
    assert np.abs(thetas(objects_only) - thetas(start)).max() > np.abs(thetas(with_pair) - thetas(start)).max()


def test_observation_of_a_frame_pair_reads_bases_and_the_closed_fingers(frames) -> None:
    from softgrip_vision.frames import load_frame

    open_path, closed_path = frames["pairs"][3]
    obs = observations_from_frames(load_frame(open_path), load_frame(closed_path), None, N, "p")
    true_bases = np.array([[-3.0 - SEPARATION / 2, -36.0], [-3.0 + SEPARATION / 2, -36.0]])
    np.testing.assert_allclose(obs.bases, true_bases, atol=0.5)
    truth = np.stack([free_closure_joints(entry(TRUE[side]), base, side) for side, base in
                      zip(("left", "right"), true_bases)])
    assert np.abs(obs.observed - truth).max() < 0.8
    assert float(jnp.min(obs.sdf.values)) == FAR_MM  # no object in that open frame


def run_cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="softgrip")
    cmd_calibrate.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["calibrate", *argv])
    return args.func(args)


@pytest.mark.slow  # runs the one-frame and fit commands end to end: about 90 s
def test_cli_one_frame_then_fit(frames, tmp_path: Path, capsys) -> None:
    one = tmp_path / "one.json"
    assert run_cli([str(frames["closed"]), "--open", str(frames["open"]), "--n-links", str(N), "-o", str(one),
                    "--camera", "synthetic"]) == 0
    out = capsys.readouterr().out
    assert "Theta" in out and f"wrote {one}" in out
    assert load_profile(one).fit.method == "one-frame"
    with pytest.raises(SoftgripError, match="--n-links 20 differs from n_links = 10"):
        run_cli(["--fit", *map(str, frames["pairs"][0]), "--profile", str(one), "--n-links", "20", "-o", "x.json"])

    fitted = tmp_path / "fitted.json"
    argv = ["--fit", *(str(p) for pair in frames["pairs"] for p in pair), "--profile", str(one), "--json",
            "--uniform", "-o", str(fitted)]  # (the stiffness model's choice: the next test)
    assert run_cli(argv) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["output"] == str(fitted)
    assert report["profile"] == load_profile(fitted).to_dict()
    # The one-frame calibration's pair (it records the folders) joins the fit as the free closure.
    calibration = f"{frames['open']} + {frames['closed']}"
    assert f"including the free-closure pair {calibration} that {one} records" in captured.err
    assert report["profile"]["fit"]["frames"][-1] == report["profile"]["fit"]["free_closure"] == calibration
    assert len(report["profile"]["fit"]["frames"]) == 5
    assert [row["frame"] for row in report["frames"]] == report["profile"]["fit"]["frames"]
    assert report["free_closure"]["frame"] == calibration and report["free_closure"]["start"] == "one-frame"
    assert "closed_empty" in report["profile"]["fit"]["skipped"][0]["frame"]
    assert "model_selection" not in report["profile"]["fit"]  # --uniform: given, not chosen
    assert "softgrip calibrate: warning:" in captured.err and "closed_empty" in captured.err
    np.testing.assert_allclose(thetas(load_profile(fitted)), [TRUE["left"], TRUE["right"]], atol=0.01)


def test_cli_fit_with_one_object_pair_keeps_the_uniform_finger_and_says_what_to_add(frames, tmp_path: Path,
                                                                                   capsys) -> None:
    """Through the mechanics estimate the pairs choose the stiffness model; one pair with an object
    cannot judge a richer model on a held-out pair, so only the uniform model is fitted and the
    report says why and what to add."""
    one = tmp_path / "one.json"
    assert run_cli([str(frames["closed"]), "--open", str(frames["open"]), "--n-links", str(N), "-o", str(one)]) == 0
    output = tmp_path / "fitted.json"
    capsys.readouterr()
    assert run_cli(["--fit", *map(str, frames["pairs"][0]), "--profile", str(one), "-o", str(output)]) == 0
    out = capsys.readouterr().out
    selection = load_profile(output).fit.model_selection
    assert selection["chosen"] == "uniform" and "1 pair(s) with an object" in selection["reason"]
    assert [c["model"] for c in selection["candidates"]] == ["uniform", "stiffness ratio",
                                                             "stiffness ratio + base compliance"]
    assert selection["candidates"][0]["residual_rms_mm"] == load_profile(output).fit.residual_rms_mm
    assert all(c["failure"].startswith("not tried") for c in selection["candidates"][1:])
    assert "stiffness model" in out and "* uniform" in out and "different heights" in out
    assert load_profile(output).fingers["left"].stiffness_ratio == 1.0


def test_cli_fit_starts_from_the_first_open_frame(frames, tmp_path: Path, capsys) -> None:
    output = tmp_path / "fitted.json"
    argv = ["--fit", *(str(p) for pair in frames["pairs"][:2] for p in pair), "--n-links", str(N), "--uniform",
            "-o", str(output)]
    assert run_cli(argv) == 0
    out = capsys.readouterr().out
    assert "least-squares: residual RMS" in out and f"({DEFAULT_METHOD} estimate)" in out
    assert load_profile(output).fit.estimate_method == DEFAULT_METHOD
    profile = load_profile(output)
    np.testing.assert_allclose(thetas(profile), [TRUE["left"], TRUE["right"]], atol=0.01)
    assert profile.fingers["left"].length == pytest.approx(LENGTH, rel=0.01)  # eq. 5 on the first open frame
    assert profile.base_separation == pytest.approx(SEPARATION, abs=0.5)
    assert profile.camera == {"name": "unspecified", "intrinsics": d405_intrinsics().to_dict()}


@pytest.mark.parametrize("argv, message", [
    (["--fit", "a", "b", "c", "-o", "p.json"], "--fit needs frame pairs OPEN CLOSED, got 3 folders"),
    (["closed", "-o", "p.json"], "give CLOSED_FRAME and --open OPEN_FRAME"),
    (["closed", "--open", "open", "--base-offset", "-o", "p.json"], "--base-offset only apply to --fit"),
    (["closed", "--fit", "a", "b", "-o", "p.json"], "with --fit give the frames as pairs"),
    (["closed", "--open", "open", "--stiffness", "-o", "p.json"], "--stiffness only apply to --fit"),
    (["closed", "--open", "open", "--uniform", "-o", "p.json"], "--uniform only apply to --fit"),
    (["--fit", "a", "b", "--uniform", "--stiffness", "-o", "p.json"], "--uniform keeps the uniform clamped finger"),
    (["closed", "--open", "open", "--empty", "o", "c", "-o", "p.json"], "--empty only apply to --fit"),
    (["closed", "--open", "open", "--method", "mechanics", "--base-compliance", "-o", "p.json"],
     "--method, --base-compliance only apply to --fit"),
])
def test_cli_usage_errors(argv, message) -> None:
    with pytest.raises(SoftgripError, match=message):
        run_cli(argv)


def test_cli_stiffness_flags_need_the_mechanics_estimate(frames, tmp_path: Path) -> None:
    pairs = [str(p) for p in frames["pairs"][0]]
    for flags, named in ((["--stiffness"], "--stiffness"), (["--base-compliance", "--stiffness"],
                                                              "--stiffness and --base-compliance"),
                          (["--uniform"], "--uniform")):
        with pytest.raises(SoftgripError, match=f"{named} only change the mechanics estimate; add --method "
                                                f"mechanics \\(the fit is going through the geometric estimate\\)"):
            run_cli(["--fit", *pairs, "--n-links", str(N), "--method", "geometric", *flags, "-o", str(tmp_path / "p.json")])


@pytest.mark.parametrize("argv, parameters, method, chosen", [
    (["--method", "mechanics"], ["theta_entire"], "mechanics", True),
    (["--method", "mechanics", "--uniform"], ["theta_entire"], "mechanics", False),
    (["--method", "mechanics", "--stiffness"], ["theta_entire", "stiffness_ratio"], "mechanics", False),
    (["--method", "mechanics", "--base-compliance", "--base-offset", "--stiffness"],
     ["theta_entire", "base_offset", "stiffness_ratio", "base_compliance"], "mechanics", False),
    (["--base-offset"], ["theta_entire", "base_offset"], DEFAULT_METHOD, DEFAULT_METHOD == "mechanics"),
    (["--method", "geometric"], ["theta_entire"], "geometric", False),
])
def test_cli_fit_passes_the_method_and_parameters(frames, tmp_path: Path, monkeypatch, capsys, argv, parameters,
                                                  method, chosen) -> None:
    """The command's wiring to softgrip_calib.fit.fit, and to softgrip_calib.select.fit_stiffness_model when the
    mechanics fit is given no stiffness flag (the fits themselves are tested in test_fit_mechanics
    and test_select)."""
    import softgrip_calib.fit
    import softgrip_calib.select

    calls = []

    def fake(kind):
        def fake_fit(observations, start, parameters, **kwargs):
            name = kwargs["estimator"].name  # the command passes the estimator object (--method mapped once)
            calls.append((kind, list(parameters), name))
            return dataclasses.replace(start, fit=FitEntry("least-squares", [o.label for o in observations],
                                                           residual_rms_mm=0.0, estimate_method=name))
        return fake_fit

    monkeypatch.setattr(softgrip_calib.fit, "fit", fake("given"))
    monkeypatch.setattr(softgrip_calib.select, "fit_stiffness_model", fake("chosen"))
    output = tmp_path / "p.json"
    pairs = [str(p) for pair in frames["pairs"][:2] for p in pair]
    assert run_cli(["--fit", *pairs, "--n-links", str(N), *argv, "-o", str(output)]) == 0
    assert calls == [("chosen" if chosen else "given", parameters, method)]
    assert load_profile(output).fit.estimate_method == method
    assert f"({method} estimate)" in capsys.readouterr().out


def test_one_frame_refuses_an_open_finger_that_is_bent() -> None:
    """Eq. 5 takes the open finger's base-tip distance as L: a bent 'open' finger (here a PCC arc of
    Theta 0.5, whose chord is L sin(Theta) / Theta, 4 % short) must not be read as a short finger."""
    closed = [keypoints((-30.0, -40.0), 0.6, "left"), keypoints((30.0, -40.0), 0.6, "right")]
    opened = [keypoints((-30.0, -40.0), 0.0, "left"), keypoints((30.0, -40.0), 0.5, "right")]
    with pytest.raises(SoftgripError, match="right finger of the open frame is not straight"):
        one_frame_profile(closed, opened, N)
    opened[1] = keypoints((30.0, -40.0), 0.1, "right")  # 0.2 % short: a straight finger's measuring noise
    assert one_frame_profile(closed, opened, N).fingers["right"].length == pytest.approx(LENGTH * math.sin(0.1) / 0.1,
                                                                                  rel=1e-4)
