"""Multi-frame calibration of the mechanics estimate, judged on held-out frames (issue 7).

Run from the repository root:

    .venv/bin/python benchmarks/bench_mechanics_fit.py            # uniform and profiled gripper
    .venv/bin/python benchmarks/bench_mechanics_fit.py --quick    # tiny configuration (CI test)
    .venv/bin/python benchmarks/bench_mechanics_fit.py --variant 'round fingers, flat base'  # other frames
    .venv/bin/python benchmarks/bench_mechanics_fit.py --selection  # the stiffness model chosen from 3 pairs

and paste the printed markdown into benchmarks/RESULTS.md.

The scenes are those of ``bench_calibration.py`` (circles, squares and clovers around the gripper
centre, rendered open and closed and run through the whole vision pipeline), at N = 20, for two
grippers whose observed closure is the elastic rod (``synthetic.rod``: 96 segments, its own
solver): a uniform one, and one whose bending stiffness doubles from the tip to the base
(``stiffness_ratio`` 2). For each gripper:

* one-frame calibration (eqs. 4-5) on rendered frames closed without an object and open;
* least squares on the training pairs and the calibration pair (closed without an object, as
  ``softgrip calibrate --fit`` includes it), starting from the one-frame profile: Theta through the
  geometric estimate (issue 4), and Theta plus the stiffness ratio through the mechanics estimate;
* the same estimate from the true geometry (the rod's L, r, Theta and stiffness ratio, the true bases
  and polygon), so the vision's cost shows in one run, and each profile's closure without an object
  against the true one at i = N/2 and N;
* on the held-out pairs: eq. 10 at i = N/2 and i = N (mean over fingers) between the estimate from
  the open frame and the rod's observed joints, and the share of fingers whose estimated contact
  case is the rod's (the rod's case from where it touches, as in ``reproduce_paper.py``).

With ``--selection``: what ``softgrip calibrate --fit`` does by default through the mechanics
estimate, from 3 training pairs and the calibration pair, on grippers that need more than a
uniform clamped finger and on ones that do not: the stiffness model the pairs choose
(:func:`softgrip_calib.select.fit_stiffness_model`), against the uniform model (Theta only) and against a fit
of Theta with the gripper's true stiffness profile and base compliance held fixed (the same
estimate on its true stiffness), each judged on the held-out pairs.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bench_calibration as bc  # noqa: E402
from softgrip_calib.fit import fit  # noqa: E402
from softgrip_calib.profile import CalibrationProfile  # noqa: E402
from reproduce_paper import rod_case  # noqa: E402
from softgrip_jax import CASE_NAMES, FingerFrame, estimate_in_frame, joint_errors  # noqa: E402
from synthetic.rod import RodMechanics  # noqa: E402
from softgrip_jax import as_estimator

_estimate = eqx.filter_jit(estimate_in_frame)


def held_out(profile: CalibrationProfile, pairs: list, method: str, n_links: int, truth: bool = False) -> dict:
    """Mean eq. 10 error (mm) at i = N/2 and i = N and the contact-case agreement with the rod;
    with ``truth``, from each pair's true geometry (bases and polygon) instead of its frames."""
    mid, tip, agree, differ = [], [], [], []
    for pair in pairs:
        observation = pair.true_observation if truth else pair.observation
        bases = profile.corrected_bases(observation.bases)
        for k, (side, hand) in enumerate(zip(bc.SIDES, (1.0, -1.0))):
            frame = FingerFrame(origin=jnp.asarray(bases[k], jnp.float32), angle=jnp.zeros(()),
                                handedness=jnp.asarray(hand))
            est = _estimate(profile.fingers[side].model(), observation.sdf, frame, estimator=as_estimator(method=method))
            errors = np.asarray(joint_errors(est.joints, jnp.asarray(pair.truth[k], jnp.float32)))
            mid.append(errors[n_links // 2])
            tip.append(errors[n_links])
            rod = rod_case(pair.rod_in_contact[k], n_links)
            agree.append(int(est.case) == rod)
            if not agree[-1]:
                differ.append(f"{pair.observation.label} {side}: {CASE_NAMES[int(est.case)]} (rod {CASE_NAMES[rod]})")
    return {"mid": float(np.mean(mid)), "tip": float(np.mean(tip)), "agree": float(np.mean(agree)),
            "fingers": len(agree), "differ": differ}


def free_closure_error(profile: CalibrationProfile, truth: CalibrationProfile, n_links: int) -> str:
    """The largest distance over both fingers between ``profile``'s closure without an object and
    the true one (the rod's free closure is the PCC arc of the true L and Theta), at joint N/2 and
    N, from the base along the gripper's axes: "mid / tip" in mm."""
    from softgrip_calib.one_frame import free_closure_joints

    gaps = [np.hypot(*(free_closure_joints(profile.fingers[side], np.zeros(2), side)
                       - free_closure_joints(truth.fingers[side], np.zeros(2), side)).T) for side in bc.SIDES]
    return f"{max(g[n_links // 2] for g in gaps):.3f} / {max(g[n_links] for g in gaps):.3f}"


def run_gripper(stiffness_ratio: float, n_links: int, n_train: int, n_test: int,
                variant: str = "default") -> list[str]:
    from vision_accuracy import VARIANTS

    options = dict(VARIANTS[variant])
    rod = RodMechanics(stiffness_ratio=stiffness_ratio)
    t0 = time.perf_counter()
    pairs = [p for p in (bc.make_pair(i, n_links, rod, options) for i in range(n_train + n_test)) if p is not None]
    train, test = pairs[:-n_test], pairs[-n_test:]
    one_frame, calibration_pair = bc.one_frame_calibration_with_pair(n_links, options)
    scenes_s = time.perf_counter() - t0

    def least_squares(parameters, method):
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # skipped pairs are counted in the table
            profile = fit([p.observation for p in train] + [calibration_pair], one_frame, parameters,
                          estimator=as_estimator(method=method),
                          progress=False)
        return profile, time.perf_counter() - t

    geometric, geometric_s = least_squares(("theta_entire",), "geometric")
    mechanics, mechanics_s = least_squares(("theta_entire", "stiffness_ratio"), "mechanics")
    true_fingers = {side: dataclasses.replace(one_frame.fingers[side], length=bc.LENGTH, theta_entire=bc.THETA[side],
                                              half_thickness=bc.HALF_THICKNESS, stiffness_ratio=stiffness_ratio)
                    for side in bc.SIDES}
    true_profile = dataclasses.replace(one_frame, fingers=true_fingers, base_separation=bc.SEPARATION)
    rows = [
        ("true geometry (the rod's L, r, Theta, ratio; true bases and polygon)", true_profile, "mechanics", None),
        ("one-frame calibration", one_frame, "geometric", None),
        ("one-frame calibration", one_frame, "mechanics", None),
        ("least squares: Theta", geometric, "geometric", geometric_s),
        ("least squares: Theta + stiffness ratio", mechanics, "mechanics", mechanics_s),
    ]
    lines = [f"#### Rod stiffness ratio {stiffness_ratio:g} (true Theta 0.55 / 0.45 rad), frames rendered as "
             f"'{variant}': {len(train)} training pairs, {len(test)} held out, N = {n_links}\n",
             "| profile | estimate | Theta left / right (rad) | stiffness ratio left / right (SE) | pairs used "
             "(skipped) | fit time (s) | held-out error i=N/2 (mm) | held-out error i=N (mm) | case agreement "
             "| free closure vs truth i=N/2 / i=N (mm) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    differ = {}
    for name, profile, method, seconds in rows:
        result = held_out(profile, test, method, n_links, truth=profile is true_profile)
        differ[f"{name}, {method}"] = result["differ"]
        f = profile.fingers
        se = profile.fit.standard_errors
        ratio = f"{f['left'].stiffness_ratio:.2f} / {f['right'].stiffness_ratio:.2f}"
        if "left.stiffness_ratio" in se:
            ratio += f" ({se['left.stiffness_ratio']:.2f} / {se['right.stiffness_ratio']:.2f})"
        used = f"{len(profile.fit.frames)} ({len(profile.fit.skipped)})"
        lines.append(f"| {name} | {method} | {f['left'].theta_entire:.4f} / {f['right'].theta_entire:.4f} | {ratio} "
                     f"| {used} | {'-' if seconds is None else f'{seconds:.0f}'} | {result['mid']:.2f} "
                     f"| {result['tip']:.2f} | {100 * result['agree']:.0f} % of {result['fingers']} "
                     f"| {free_closure_error(profile, true_profile, n_links)} |")
    lines.append("\nFingers whose case differs from the rod's: "
                 + "; ".join(f"{row}: {', '.join(d)}" for row, d in differ.items() if d) + ".")
    lines.append(f"\n(scenes, rod closures and rendering: {scenes_s:.0f} s; fit times include compilation)\n")
    return lines


#: (stiffness ratio, base compliance) of the grippers of ``--selection``: uniform and clamped (the
#: paper's finger), stiffer at the base, and stiffer at the base on a compliant clamp.
SELECTION_GRIPPERS = ((1.0, 0.0), (2.0, 0.0), (2.0, 0.3))


def run_selection(stiffness_ratio: float, base_compliance: float, n_links: int, n_train: int, n_test: int,
                  variant: str = "default") -> list[str]:
    from softgrip_calib.select import fit_stiffness_model
    from vision_accuracy import VARIANTS

    options = dict(VARIANTS[variant])
    rod = RodMechanics(stiffness_ratio=stiffness_ratio, base_compliance=base_compliance)
    t0 = time.perf_counter()
    pairs = [p for p in (bc.make_pair(i, n_links, rod, options) for i in range(n_train + n_test)) if p is not None]
    train, test = pairs[:-n_test], pairs[-n_test:]
    one_frame, calibration_pair = bc.one_frame_calibration_with_pair(n_links, options)
    scenes_s = time.perf_counter() - t0
    data = [p.observation for p in train] + [calibration_pair]

    def timed(make):
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                return make(), time.perf_counter() - t, None
            except Exception as err:  # a fit that fails is a row of the table, not the end of the run
                return None, time.perf_counter() - t, f"{type(err).__name__}: {err}"

    true_stiffness = dataclasses.replace(one_frame, fingers={
        side: dataclasses.replace(one_frame.fingers[side], stiffness_ratio=stiffness_ratio,
                                  base_compliance=base_compliance) for side in bc.SIDES})
    rows = [
        ("one-frame calibration (uniform)", *timed(lambda: one_frame)),
        ("least squares: Theta, true stiffness held", *timed(lambda: fit(data, true_stiffness, ("theta_entire",),
                                                                         progress=False))),
        ("least squares: Theta, uniform", *timed(lambda: fit(data, one_frame, ("theta_entire",), progress=False))),
        ("default --fit (model chosen)", *timed(lambda: fit_stiffness_model(data, one_frame, progress=False))),
    ]
    reference = None if rows[1][1] is None else held_out(rows[1][1], test, "mechanics", n_links)
    lines = [f"#### Rod stiffness ratio {stiffness_ratio:g}, base compliance {base_compliance:g} (true Theta 0.55 / "
             f"0.45 rad), frames rendered as '{variant}': {len(train)} training pairs + the calibration pair, "
             f"{len(test)} held out, N = {n_links}\n",
             "| profile | Theta left / right (rad) | stiffness ratio left / right | base compliance left / right "
             "| fit time (s) | held-out error i=N/2 (mm) | held-out error i=N (mm) | i=N against true stiffness (mm) "
             "| case agreement |",
             "|---|---|---|---|---|---|---|---|---|"]
    notes = []
    for name, profile, seconds, failure in rows:
        if profile is None:
            lines.append(f"| {name} | failed | | | {seconds:.0f} | | | | |")
            notes.append(f"{name}: {failure}")
            continue
        result = held_out(profile, test, "mechanics", n_links)
        f = profile.fingers
        selection = profile.fit.model_selection
        if selection is not None:
            name = f"default --fit: chose '{selection['chosen']}'"
            notes.append(f"{name}: " + "; ".join(
                f"{c['model']} held out {'-' if c['held_out_rms_mm'] is None else format(c['held_out_rms_mm'], '.3f')}"
                f" mm" + (f" ({c['failure']})" if c["failure"] else "") for c in selection["candidates"]))
        against = "-" if reference is None else f"{result['tip'] - reference['tip']:+.2f}"
        lines.append(f"| {name} | {f['left'].theta_entire:.4f} / {f['right'].theta_entire:.4f} "
                     f"| {f['left'].stiffness_ratio:.2f} / {f['right'].stiffness_ratio:.2f} "
                     f"| {f['left'].base_compliance:.3f} / {f['right'].base_compliance:.3f} "
                     f"| {'-' if profile is one_frame else f'{seconds:.0f}'} | {result['mid']:.2f} | {result['tip']:.2f} "
                     f"| {against} | {100 * result['agree']:.0f} % of {result['fingers']} |")
    lines.append("\n" + "\n".join(f"- {n}" for n in notes))
    lines.append(f"\n(scenes, rod closures and rendering: {scenes_s:.0f} s; fit times include compilation)\n")
    return lines


def main(argv: list[str] | None = None) -> str:
    from _machine import describe

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny configuration: N = 4, 3 + 2 pairs, one gripper")
    parser.add_argument("--variant", default="default", metavar="NAME",
                        help="render the frames as this variant of benchmarks/vision_accuracy.py (one whose gripper "
                             "plane faces the camera and whose tips do not touch), e.g. 'round fingers, flat base'")
    parser.add_argument("--selection", action="store_true",
                        help="the stiffness model chosen by the default fit from 3 pairs, on grippers with and "
                             "without a stiffer base and a compliant clamp")
    args = parser.parse_args(argv)
    from vision_accuracy import VARIANTS

    usable = [name for name, options in VARIANTS.items() if not {"tilt_deg", "touching"} & set(options)]
    if args.variant not in usable:
        parser.error(f"--variant must be one of: {', '.join(repr(v) for v in usable)}")
    if args.quick:
        configs, n_links, n_train, n_test = (2.0,), 4, 3, 2
    else:
        configs, n_links, n_train, n_test = (1.0, 2.0), 20, 16, 24
    t0 = time.perf_counter()
    lines = ["Command (from the repository root):\n",
             "    .venv/bin/python benchmarks/bench_mechanics_fit.py" + (" --quick" if args.quick else "")
             + (" --selection" if args.selection else "")
             + ("" if args.variant == "default" else f" --variant '{args.variant}'") + "\n",
             f"Machine: {describe()}\n"]
    if args.selection:
        grippers = SELECTION_GRIPPERS[2:3] if args.quick else SELECTION_GRIPPERS
        for ratio, compliance in grippers:
            lines += run_selection(ratio, compliance, n_links, 3, n_test, args.variant)
            print(f"gripper ({ratio:g}, {compliance:g}) done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        configs = ()
    for ratio in configs:
        lines += run_gripper(ratio, n_links, n_train, n_test, args.variant)
        print(f"gripper with stiffness ratio {ratio:g} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    lines.append(f"Whole run: {time.perf_counter() - t0:.0f} s.")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    main()
