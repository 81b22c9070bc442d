"""Which vision input biases the stiffness ratio fitted through frames (issue 19).

Run from the repository root:

    .venv/bin/python benchmarks/stiffness_sensitivity.py            # rod stiffness ratio 2
    .venv/bin/python benchmarks/stiffness_sensitivity.py --ratio 1

The 16 training pairs of ``bench_mechanics_fit.py`` (rendered, through the whole vision pipeline)
are fitted for Theta and the stiffness ratio through the mechanics estimate, as they are, and with
each input replaced by the renderer's truth in turn: the one-frame calibration's L and r, the
closed frames' observed joints, the open frames' bases, the object's signed distance. A ratio that
moves far when one input becomes true says how much of the bias that input carries.
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

import bench_calibration as bc  # noqa: E402
from calib.fit import fit  # noqa: E402
from vision.synthetic.rod import RodMechanics  # noqa: E402


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
             "| inputs | fitted ratio left / right | fitted Theta left / right (rad) |", "|---|---|---|"]
    for name, observations, start in cases:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            profile = fit(observations, start, ("theta_entire", "stiffness_ratio"), method="mechanics", progress=False)
        f = profile.fingers
        lines.append(f"| {name} | {f['left'].stiffness_ratio:.3f} / {f['right'].stiffness_ratio:.3f} "
                     f"| {f['left'].theta_entire:.4f} / {f['right'].theta_entire:.4f} |")
    lines.append(f"\nWhole run: {time.perf_counter() - t0:.0f} s.")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    main()
