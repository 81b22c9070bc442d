"""Calibration: the least-squares fit's time, and whether it beats the one-frame calibration.

Run from the repository root:

    .venv/bin/python benchmarks/bench_calibration.py      # about 1.5 minutes on 2 cores

and paste the printed markdown into benchmarks/RESULTS.md.

A two-finger gripper (L = 52 mm, r = 4 mm, bases 64 mm apart, Theta 0.55 rad left and 0.45 rad
right) closes on circles, squares and clovers placed around the gripper centre. The "observed"
closure of every finger is the elastic-rod model (``synthetic.rod.close_rod``: clamped,
uniform stiffness, frictionless contact), independent of the estimator. Every scene is rendered
twice (open with the object, closed on it) and goes through the whole vision pipeline
(segmentation, keypoints, object SDF grid), so the fit sees what it would see from a camera.

* one-frame calibration: eq. 4 on a rendered frame of the gripper closed without an object, and
  eq. 5 on an open frame;
* least squares: Theta of both fingers (and, in a second variant, a base offset per finger) fitted
  to the first 6 training pairs, and to all 20, starting from the one-frame profile;
* evaluation on 8 held-out scenes: mean over joints i = 1..N and fingers of eq. 10's error between
  the estimate from the open frame (bases and object SDF from the vision pipeline) and the rod's
  joints (the closure divided into N equal arc lengths), and the same at the tip (i = N). "true
  Theta" is the estimate with the rod's own Theta: the estimator's model error alone.

Fit timings are of a 20-pair fit (theta only): the first call (compilation included) and the
median of three later calls.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from softgrip_calib.fit import Observation, fit, free_closure_observation, observations_from_frames
from softgrip_calib.one_frame import one_frame_from_frames
from softgrip_calib.profile import CalibrationProfile
from softgrip_jax import CASE_NAMES, FingerFrame, PolygonSDF, estimate_in_frame, joint_errors
from softgrip_vision.keypoints import resample_polyline
_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:  # the test support `synthetic` sits at the root of the checkout
    sys.path.insert(0, _ROOT)
from synthetic.render import Scene, d405_intrinsics, render  # noqa: E402
from synthetic.rod import RodMechanics, close_rod, free_arc_points, observed_joints  # noqa: E402
from synthetic.scenes import gripper_centrelines  # noqa: E402
from synthetic.shapes import shape  # noqa: E402
from softgrip_jax import Geometric

LENGTH, HALF_THICKNESS, SEPARATION, N_LINKS = 52.0, 4.0, 64.0, 10
THETA = {"left": 0.55, "right": 0.45}
SIDES = ("left", "right")
OBJECTS = ("circle", "square", "clover")
N_VERTICES = 96  # one rod compilation for every object
N_TRAIN, N_SMALL, N_TEST = 20, 6, 8
INTRINSICS = d405_intrinsics()


@dataclass(frozen=True)
class Pair:
    """One scene: its observation through the vision pipeline and the rod's true joints (2, N+1, 2)."""

    observation: Observation
    truth: np.ndarray
    rod_in_contact: tuple = ()  # each finger's rod nodes in contact (M+1,), for the rod's contact case
    true_observation: Observation | None = None  # the same pair from the renderer's geometry (bases, polygon)


def make_pair(index: int, n_links: int = N_LINKS, rod: RodMechanics = RodMechanics(),
              scene_options: dict | None = None) -> Pair | None:
    """Scene ``index``: render it open and closed (rod closures with ``rod``'s stiffness profile and
    base compliance), observed at ``n_links``; None if a closure fails. ``scene_options``: more
    ``Scene`` fields for both frames (a renderer variant, e.g. round fingers; the gripper plane must
    face the camera, so that the renderer's millimetres are the pipeline's)."""
    rng = np.random.default_rng(500 + index)
    center = np.array([rng.uniform(-10.0, 10.0), rng.uniform(-48.0, -38.0)])
    name = OBJECTS[index % len(OBJECTS)]
    outline = shape(name, rng.uniform(24.0, 32.0), rng.uniform(0.0, 2.0 * math.pi))
    outline = outline + center + (rng.uniform(-5.0, 5.0), rng.uniform(0.5, 0.8) * LENGTH)
    polygon = resample_polyline(np.vstack([outline, outline[:1]]), N_VERTICES)[:-1]
    sdf = PolygonSDF(jnp.asarray(polygon))
    bases = center + np.array([[-SEPARATION / 2, 0.0], [SEPARATION / 2, 0.0]])
    closures = [close_rod(base, THETA[side], LENGTH, HALF_THICKNESS, sdf, handedness=hand, mechanics=rod)
                for side, base, hand in zip(SIDES, bases, (1.0, -1.0))]
    if not all(bool(c.converged) for c in closures):
        return None
    options = scene_options or {}
    opened = Scene(gripper_centrelines(tuple(center), SEPARATION, LENGTH), half_thickness=HALF_THICKNESS,
                   object_polygon=polygon, seed=2 * index, **options)
    closed = Scene([np.asarray(c.points) for c in closures], half_thickness=HALF_THICKNESS,
                   object_polygon=polygon, seed=2 * index + 1, **options)
    observation = observations_from_frames(render(opened, INTRINSICS), render(closed, INTRINSICS), None, n_links,
                                           f"scene {index} ({name})")
    truth = np.stack([np.asarray(observed_joints(c, n_links)) for c in closures])
    return Pair(observation, truth, tuple(np.asarray(c.in_contact) for c in closures),
                Observation(sdf=sdf, bases=bases, observed=truth, label=f"scene {index} ({name}), true geometry"))


def one_frame_calibration(n_links: int = N_LINKS, scene_options: dict | None = None) -> CalibrationProfile:
    """Eqs. 4-5 on rendered frames: the gripper closed without an object, and open (``scene_options``
    as for :func:`make_pair`)."""
    return one_frame_calibration_with_pair(n_links, scene_options)[0]


def one_frame_calibration_with_pair(n_links: int = N_LINKS, scene_options: dict | None = None
                                    ) -> tuple[CalibrationProfile, Observation]:
    """:func:`one_frame_calibration` and its frame pair as a fit's free-closure observation."""
    options = scene_options or {}
    arcs = {side: np.asarray(free_arc_points((0.0, 0.0), THETA[side], LENGTH, np.linspace(0.0, LENGTH, 257)))
            for side in SIDES}
    closed = Scene(gripper_centrelines((0.0, -40.0), SEPARATION, LENGTH, left_shape=arcs["left"],
                                       right_shape=arcs["right"]), half_thickness=HALF_THICKNESS, seed=9001,
                   **options)
    opened = Scene(gripper_centrelines((0.0, -40.0), SEPARATION, LENGTH), half_thickness=HALF_THICKNESS, seed=9002,
                   **options)
    closed_frame, open_frame = render(closed, INTRINSICS), render(opened, INTRINSICS)
    profile = one_frame_from_frames(closed_frame, open_frame, n_links, label="synthetic closed + open",
                                    camera_name="synthetic")
    return profile, free_closure_observation(open_frame, closed_frame, None, n_links, "calibration pair")


_estimate = eqx.filter_jit(estimate_in_frame)


def held_out_errors(profile: CalibrationProfile, pairs: list[Pair]) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 10 errors (fingers, N) in mm at joints 1..N of the estimates with ``profile``, and each
    finger's estimated contact case (fingers,)."""
    errors, cases = [], []
    for pair in pairs:
        bases = profile.corrected_bases(pair.observation.bases)
        for k, (side, hand) in enumerate(zip(SIDES, (1.0, -1.0))):
            frame = FingerFrame(origin=jnp.asarray(bases[k], jnp.float32), angle=jnp.zeros(()),
                                handedness=jnp.asarray(hand))
            est = _estimate(profile.fingers[side].model(), pair.observation.sdf, frame, estimator=Geometric())
            errors.append(np.asarray(joint_errors(est.joints, jnp.asarray(pair.truth[k], jnp.float32)))[1:])
            cases.append(int(est.case))
    return np.array(errors), np.array(cases)


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _machine import describe

    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    print("Command (from the repository root):\n\n    .venv/bin/python benchmarks/bench_calibration.py\n")
    print(f"Machine: {describe()}\n")
    t0 = time.perf_counter()

    pairs = []
    for index in range(N_TRAIN + N_TEST):
        pair = make_pair(index)
        if pair is not None:
            pairs.append(pair)
        print(f"\rscenes: {index + 1}/{N_TRAIN + N_TEST}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    dropped = N_TRAIN + N_TEST - len(pairs)
    train, test = pairs[:-N_TEST], pairs[-N_TEST:]
    one_frame = one_frame_calibration()
    scenes_s = time.perf_counter() - t0

    def run_fit(pairs_, parameters=("theta_entire",)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # skipped pairs are counted in the table
            return fit([p.observation for p in pairs_], one_frame, parameters, estimator=Geometric(), progress=False)

    t = time.perf_counter()
    fitted_all = run_fit(train)
    first_s = time.perf_counter() - t
    repeats = []
    for _ in range(3):
        t = time.perf_counter()
        run_fit(train)
        repeats.append(time.perf_counter() - t)
    steady_s = statistics.median(repeats)
    fitted_small = run_fit(train[:N_SMALL])
    fitted_offset = run_fit(train[:N_SMALL], ("theta_entire", "base_offset"))
    true_theta = replace(one_frame, fingers={s: replace(f, theta_entire=THETA[s]) for s, f in one_frame.fingers.items()})

    rows = [
        ("true Theta (model error only)", true_theta),
        ("one-frame calibration (eqs. 4-5)", one_frame),
        (f"least squares, Theta, {N_SMALL} pairs", fitted_small),
        (f"least squares, Theta + base offset, {N_SMALL} pairs", fitted_offset),
        (f"least squares, Theta, {len(train)} pairs", fitted_all),
    ]
    print(f"### Calibration on rod closures ({len(train)} training scenes, {len(test)} held out"
          f"{f', {dropped} dropped: rod not converged' if dropped else ''})\n")
    print("| profile | pairs used (skipped) | Theta left (rad) | Theta right (rad) | SE left / right (rad) "
          "| fit residual RMS (mm) | held-out mean joint error (mm) | held-out tip error (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    by_case = {}
    for name, profile in rows:
        errors, cases = held_out_errors(profile, test)
        mean_error, tip_error = errors.mean(), errors[:, -1].mean()
        by_case[name] = (errors.mean(axis=1), cases)
        se = profile.fit.standard_errors
        se_text = f"{se['left.theta_entire']:.4f} / {se['right.theta_entire']:.4f}" if se else "-"
        rms = "-" if profile is true_theta or profile.fit.residual_rms_mm is None else f"{profile.fit.residual_rms_mm:.2f}"
        used = "-" if profile is true_theta else f"{len(profile.fit.frames)} ({len(profile.fit.skipped)})"
        print(f"| {name} | {used} | {profile.fingers['left'].theta_entire:.4f} | {profile.fingers['right'].theta_entire:.4f} "
              f"| {se_text} | {rms} | {mean_error:.2f} | {tip_error:.2f} |")
    offsets = ", ".join(f"{s} ({fitted_offset.fingers[s].base_offset[0]:+.2f}, "
                        f"{fitted_offset.fingers[s].base_offset[1]:+.2f}) mm" for s in SIDES)
    print(f"\nFitted base offsets ({N_SMALL} pairs): {offsets}. True Theta: left {THETA['left']}, right {THETA['right']} "
          f"rad. The one-frame row's residual is the PCC fit to its closed frame.\n")
    _, reference_cases = by_case[rows[1][0]]
    present = sorted(set(reference_cases.tolist()))
    print("Held-out mean joint error (mm) by the contact case of the one-frame estimate (number of fingers):\n")
    print("| profile | " + " | ".join(f"{CASE_NAMES[c]} ({int(np.sum(reference_cases == c))})" for c in present) + " |")
    print("|---|" + "---|" * len(present))
    for name, (finger_errors, _) in by_case.items():
        print(f"| {name} | " + " | ".join(f"{finger_errors[reference_cases == c].mean():.2f}" for c in present) + " |")
    print()
    print(f"### Fit time, {len(train)} frame pairs (Theta of both fingers, float64, 480 x 640 SDF grids)\n")
    print("| first call (compiles) | compile (first - later) | later calls (median of 3) |")
    print("|---|---|---|")
    print(f"| {first_s:.1f} s | {first_s - steady_s:.1f} s | {steady_s:.2f} s |")
    print(f"\n(scenes, rod closures and rendering: {scenes_s:.0f} s; whole run: {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
