"""How the physics plausibility checks (issue 32) fare on rendered frames: false alarms on frames the
right way up, refusals of the same frames upside down, and how far the measured sizes lie from the
renderer's (what the profile tolerances must leave room for).

Run from the repository root:

    .venv/bin/python benchmarks/plausibility_sweep.py             # 3 seeds per set-up (about a minute)
    .venv/bin/python benchmarks/plausibility_sweep.py --seeds 5

and paste the printed markdown into a RESULTS file. Every frame goes through
``softgrip_vision.scene.frame_scene`` with a profile of the rendered gripper's own sizes (so a refusal of an
upright frame is a false alarm), then flipped vertically and rotated by 180 degrees.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from softgrip_calib.profile import load_profile
from softgrip_jax import SoftgripError
from synthetic.render import Scene, d405_intrinsics, render
from synthetic.scenes import gripper_centrelines
from softgrip_vision.frames import Frame
from softgrip_vision.scene import frame_scene

ROOT = Path(__file__).resolve().parents[1]
LENGTH, HALF, SEPARATION = 52.0, 4.0, 64.0

#: The renderer's set-ups: the gripper's body in view or not, base ends, finger sections, camera.
SETUPS = {
    "rounded ends, no body (data/)": {},
    "round fingers, rounded ends": {"finger_section": "round"},
    "flat-cut bases, no body": {"base_end": "flat"},
    "flat-cut bases, round fingers": {"base_end": "flat", "finger_section": "round"},
    "body in view (20 mm)": {"palm": True, "palm_height_mm": 20.0, "base_end": "flat"},
    "body in view (12 mm), round": {"palm": True, "palm_height_mm": 12.0, "base_end": "flat", "finger_section": "round"},
    "flat-cut bases, camera tilted 8/-5 deg": {"base_end": "flat", "tilt_deg": (8.0, -5.0)},
    "flat-cut bases, depth blur 1.7 px": {"base_end": "flat", "depth_blur_px": 1.7},
    "flat-cut bases, anti-aliased, uneven light": {"base_end": "flat", "supersample": 3, "light_gradient": 0.3},
    "flat-cut bases, 160 mm away, L 45 mm": {"base_end": "flat", "plane_depth_mm": 160.0, "length": 45.0},
}


def _profile(length: float):
    base = load_profile(ROOT / "data" / "sample_profile.json")
    fingers = {s: dataclasses.replace(f, length=length, half_thickness=HALF) for s, f in base.fingers.items()}
    return dataclasses.replace(base, fingers=fingers, base_separation=SEPARATION)


def _frame(setup: dict, seed: int) -> tuple[Frame, float]:
    setup = dict(setup)
    length = setup.pop("length", LENGTH)
    t = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    disc = np.column_stack([15.0 * np.cos(t), -20.0 + 15.0 * np.sin(t)])
    scene = Scene(gripper_centrelines((0.0, -45.0), SEPARATION, length, 64), half_thickness=HALF,
                  object_polygon=disc, object_rgb=(235, 170, 30), seed=seed, **setup)
    return render(scene, d405_intrinsics()), length


def _turned(frame: Frame, how: str) -> Frame:
    def op(a):
        return np.ascontiguousarray(a[::-1] if how == "flipud" else a[::-1, ::-1])

    return Frame(op(frame.color), op(frame.depth), frame.intrinsics)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="frames per set-up (default 3)")
    args = parser.parse_args()
    start = time.perf_counter()
    print("| set-up | upright refused | flipud refused | rot180 refused | arc length - L (mm, max abs) | "
          "r - r_true (mm, max abs) |")
    print("|---|---|---|---|---|---|")
    totals = np.zeros(3, int)
    for name, setup in SETUPS.items():
        refused = np.zeros(3, int)
        length_err, thick_err = [], []
        for seed in range(args.seeds):
            frame, length = _frame(setup, seed)
            profile = _profile(length)
            for k, how in enumerate(("upright", "flipud", "rot180")):
                try:
                    scene = frame_scene(frame if how == "upright" else _turned(frame, how), profile, warn=lambda m: None)
                except SoftgripError:
                    refused[k] += 1
                    continue
                if how == "upright":
                    length_err += [abs(kp.arc_length_mm - length) for kp in scene.keypoints]
                    thick_err += [abs(kp.half_thickness_mm - HALF) for kp in scene.keypoints]
        totals += refused
        n = args.seeds
        print(f"| {name} | {refused[0]}/{n} | {refused[1]}/{n} | {refused[2]}/{n} | "
              f"{max(length_err, default=float('nan')):.2f} | {max(thick_err, default=float('nan')):.2f} |")
    n = args.seeds * len(SETUPS)
    print(f"\nAll set-ups: upright refused {totals[0]}/{n}, flipud {totals[1]}/{n}, rot180 {totals[2]}/{n} "
          f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
