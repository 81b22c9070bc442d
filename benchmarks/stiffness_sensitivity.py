"""Which vision input biases the stiffness ratio fitted through frames (issue 19).

Run from the repository root:

    .venv/bin/python benchmarks/stiffness_sensitivity.py            # rod stiffness ratio 2
    .venv/bin/python benchmarks/stiffness_sensitivity.py --ratio 1

The 16 training pairs of ``bench_mechanics_fit.py`` (rendered, through the whole vision pipeline)
are fitted for Theta and the stiffness ratio through the mechanics estimate, as they are, and with
each input replaced by the renderer's truth in turn: the one-frame calibration's L and r, the
closed frames' observed joints, the open frames' bases, the object's signed distance. A ratio that
moves far when one input becomes true says how much of the bias that input carries.

Then how much the frames can say about the ratio at all: for every finger of those pairs, how far
a 5 % change of the ratio moves its joints (the mechanics estimate on the true geometry, forward
mode), in mm and in pixels of the frames, against how far vision's observed joints are from the
rod's; and the same 5 % move for a disc of radius 5, 10 or 15 mm at every place of a grid in the
finger's frame, the best placement a calibration could choose.
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

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import bench_calibration as bc  # noqa: E402
from softgrip_calib.fit import PoorlyDeterminedWarning, fit  # noqa: E402
from softgrip_jax import FingerFrame, FingerModel, PolygonSDF, estimate_in_frame  # noqa: E402
from synthetic.render import Scene  # noqa: E402
from synthetic.rod import RodMechanics  # noqa: E402
from softgrip_jax import Mechanics

CHANGE = 1.05  # the goal's 5 %


def _ratio_jacobian(ratio: float):
    """d joints / d log(ratio) (N+1, 2) mm of the left-handed true finger against ``sdf`` at ``base``."""
    def joints(log_ratio, sdf, base, hand, theta):
        finger = FingerModel(length=bc.LENGTH, theta_entire=theta, half_thickness=bc.HALF_THICKNESS, n_links=20,
                             stiffness_ratio=jnp.exp(log_ratio))
        frame = FingerFrame(origin=base, angle=jnp.zeros_like(theta), handedness=hand)
        return estimate_in_frame(finger, sdf, frame, estimator=Mechanics())
    jacobian = jax.jacfwd(lambda *a: joints(*a).joints)
    return jax.jit(lambda sdf, base, hand, theta: (jacobian(jnp.log(ratio), sdf, base, hand, theta),
                                                    joints(jnp.log(ratio), sdf, base, hand, theta).status))


def resolution(pairs: list, ratio: float) -> list[str]:
    """Per finger of ``pairs``: the largest joint move of a 5 % ratio change against vision's joint error."""
    mm_per_px = Scene.__dataclass_fields__["plane_depth_mm"].default / bc.INTRINSICS.fx
    moves, errors = [], []
    jacobian = _ratio_jacobian(ratio)
    for pair in pairs:
        true, seen = pair.true_observation, pair.observation
        sdf = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), true.sdf)
        for k, (side, hand) in enumerate(zip(bc.SIDES, (1.0, -1.0))):
            d, _ = jacobian(sdf, jnp.asarray(true.bases[k], jnp.float32), jnp.float32(hand), jnp.float32(bc.THETA[side]))
            moves.append(np.hypot(*(np.asarray(d) * np.log(CHANGE)).T).max())
            errors.append(np.sqrt(np.mean(np.sum((seen.observed[k] - true.observed[k]) ** 2, axis=-1))))
    moves, errors = np.array(moves), np.array(errors)
    return [f"\nHow far a 5 % change of the ratio moves the joints, {len(moves)} fingers of these pairs "
            f"(true geometry, ratio {ratio:g}; {mm_per_px:.3f} mm per pixel in the gripper plane):\n",
            "| | median | largest |", "|---|---|---|",
            f"| largest joint move of one finger, mm | {np.median(moves):.4f} | {moves.max():.4f} |",
            f"| the same in pixels | {np.median(moves) / mm_per_px:.3f} | {moves.max() / mm_per_px:.3f} |",
            f"| vision's observed-joint error (RMS over the finger's joints), mm | {np.median(errors):.3f} "
            f"| {errors.max():.3f} |"]


def best_placement(ratio: float) -> list[str]:
    """The largest joint move of a 5 % ratio change over discs placed on a grid in the finger's frame."""
    jacobian = _ratio_jacobian(ratio)
    hand, theta = jnp.float32(1.0), jnp.float32(bc.THETA["left"])
    lines = [f"\nThe largest joint move (mm) of a 5 % ratio change for a disc anywhere on a 5 mm grid in the left "
             f"finger's frame (x toward the closing side 0-40 mm, y down the finger 10-55 mm; discs that overlap the "
             f"open finger left out):\n", "| disc radius (mm) | largest move (mm) | at (x, y) mm |", "|---|---|---|"]
    for radius in (5.0, 10.0, 15.0):
        best = (0.0, None)
        for x in np.arange(0.0, 45.0, 5.0):
            for y in np.arange(10.0, 60.0, 5.0):
                sdf = PolygonSDF.regular((float(x), float(y)), radius, n_vertices=96)
                d, status = jacobian(sdf, jnp.zeros(2, jnp.float32), hand, theta)
                move = float(np.hypot(*(np.asarray(d) * np.log(CHANGE)).T).max())
                if int(status) == 0 and move > best[0]:
                    best = (move, f"({x:g}, {y:g})")
        lines.append(f"| {radius:g} | {best[0]:.4f} | {best[1]} |")
    return lines


def main(argv: list[str] | None = None) -> str:
    from _machine import describe

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ratio", type=float, default=2.0, help="the rod's stiffness ratio (default 2)")
    parser.add_argument("--pairs", type=int, default=16, help="training pairs (default 16)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    rod = RodMechanics(stiffness_ratio=args.ratio)
    pairs = [p for p in (bc.make_pair(i, 20, rod) for i in range(args.pairs)) if p is not None]
    one_frame = bc.one_frame_calibration(20)
    true_fingers = {side: dataclasses.replace(one_frame.fingers[side], length=bc.LENGTH, theta_entire=bc.THETA[side],
                                              half_thickness=bc.HALF_THICKNESS) for side in bc.SIDES}
    true_start = dataclasses.replace(one_frame, fingers=true_fingers, base_separation=bc.SEPARATION)
    seen = [p.observation for p in pairs]
    true = [p.true_observation for p in pairs]
    cases = [
        ("everything from the frames (one-frame L, r)", seen, one_frame),
        ("true L and r", seen, true_start),
        ("true L, r, bases and object", [dataclasses.replace(t, observed=s.observed) for s, t in zip(seen, true)],
         true_start),
        ("true L, r and observed joints", [dataclasses.replace(s, observed=t.observed) for s, t in zip(seen, true)],
         true_start),
        ("true L, r and object", [dataclasses.replace(s, sdf=t.sdf) for s, t in zip(seen, true)], true_start),
        ("true L, r and bases", [dataclasses.replace(s, bases=t.bases) for s, t in zip(seen, true)], true_start),
        ("everything true", true, true_start),
    ]
    lines = ["Command (from the repository root):\n",
             f"    .venv/bin/python benchmarks/stiffness_sensitivity.py --ratio {args.ratio:g} --pairs {args.pairs}\n",
             f"Machine: {describe()}\n",
             f"Rod stiffness ratio {args.ratio:g}, true Theta 0.55 / 0.45 rad, {len(pairs)} pairs, N = 20, mechanics "
             f"estimate; one-frame L {one_frame.fingers['left'].length:.3f} / {one_frame.fingers['right'].length:.3f} "
             f"mm, r {one_frame.fingers['left'].half_thickness:.3f} / {one_frame.fingers['right'].half_thickness:.3f} "
             f"mm (true {bc.LENGTH:g} / {bc.HALF_THICKNESS:g})\n",
             "| inputs | fitted ratio left / right (standard error) | fitted Theta left / right (rad) "
             "| reported poorly determined |", "|---|---|---|---|"]
    for name, observations, start in cases:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            profile = fit(observations, start, ("theta_entire", "stiffness_ratio"), estimator=Mechanics(), progress=False)
        f, se = profile.fingers, profile.fit.standard_errors
        poor = [side for side in bc.SIDES if any(isinstance(w.message, PoorlyDeterminedWarning)
                                                 and str(w.message).startswith(side) for w in caught)]
        lines.append(f"| {name} | {f['left'].stiffness_ratio:.3f} / {f['right'].stiffness_ratio:.3f} "
                     f"({se['left.stiffness_ratio']:.3f} / {se['right.stiffness_ratio']:.3f}) "
                     f"| {f['left'].theta_entire:.4f} / {f['right'].theta_entire:.4f} | {', '.join(poor) or '-'} |")
    lines += resolution(pairs, args.ratio) + best_placement(args.ratio)
    lines.append(f"\nWhole run: {time.perf_counter() - t0:.0f} s.")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    main()
