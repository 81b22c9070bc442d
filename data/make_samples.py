"""Regenerate the sample frames of ``data/`` (deterministic: every random draw has a fixed seed).

    .venv/bin/python data/make_samples.py            # rewrites the frames, truth.json, sample_profile.json
    .venv/bin/python data/make_samples.py --out DIR  # somewhere else

Every frame is rendered by the project's own renderer (``synthetic.render``) as a RealSense
D405 sees a gripper 120 mm away; every closed finger is the independent elastic-rod closure model
(``synthetic.rod.close_rod``), never the estimator's own model. What each frame shows and why
is in ``data/README.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # runnable from anywhere in a source checkout
    sys.path.insert(0, str(ROOT))

from softgrip_jax import PolygonSDF  # noqa: E402
from softgrip_vision.frames import load_frame, save_frame  # noqa: E402
from synthetic.render import Scene, d405_intrinsics, render  # noqa: E402
from synthetic.rod import close_rod, observed_joints  # noqa: E402
from synthetic.scenes import gripper_centrelines  # noqa: E402
from synthetic.shapes import shape  # noqa: E402

# The gripper (mm, rad). The bases are 64 mm apart, not 56: with Theta = 0.55 the free closed tips
# sit 25.8 mm inward of their bases, so at 56 mm the closed fingers of the calibration frame would
# overlap (4.4 mm between centrelines for 8 mm thick fingers) and segmentation could not tell them
# apart; at 64 mm they stay 4.4 mm apart.
LENGTH_MM = 52.0
HALF_THICKNESS_MM = 4.0
THETA = 0.55
BASE_SEPARATION_MM = 64.0
GRIPPER_CENTER_MM = (0.0, -45.0)  # midway between the finger bases, in the gripper plane
PLANE_DEPTH_MM = 120.0
N_LINKS = 20  # the sample profile's N (the paper's Experiment A-b uses 20)
# The objects' front faces lie 3 mm behind the fingers' plane (their outlines drawn there): vision
# converts an object's outline at the depth of its own face.
OBJECT_FACE_OFFSET_MM = 3.0
WIDTH, HEIGHT = 640, 480
# Orange-yellow objects: saturated (segmented as the object) and far from the overlays' colours
# (estimated joints blue, observed positions green, contacts red).
OBJECT_RGB = (235, 170, 30)


@dataclass(frozen=True)
class SampleScene:
    """One object between the open fingers: a key of ``synthetic.shapes.SHAPES``, its
    bounding-circle diameter (mm), rotation (rad), centroid (mm) and the seeds of its two frames."""

    name: str
    size_mm: float
    angle: float
    center_mm: tuple[float, float]
    seed: int

    def polygon(self) -> np.ndarray:
        return shape(self.name, self.size_mm, self.angle) + np.asarray(self.center_mm)


SCENES = (
    SampleScene("circle", 30.0, 0.0, (0.0, -20.0), seed=10),
    SampleScene("square", 34.0, 0.35, (2.0, -17.0), seed=20),
    SampleScene("star_a", 32.0, 0.0, (-3.0, -16.0), seed=30),
)
CALIBRATION_SEEDS = {"calib_open": 1, "calib_closed": 2}


def _scene(fingers: list[np.ndarray], polygon: np.ndarray | None, seed: int) -> Scene:
    return Scene(fingers, half_thickness=HALF_THICKNESS_MM, object_polygon=polygon,
                 plane_depth_mm=PLANE_DEPTH_MM, object_depth_offset_mm=OBJECT_FACE_OFFSET_MM, object_rgb=OBJECT_RGB,
                 palm=False, seed=seed)


def _closed_fingers(sdf: PolygonSDF | None) -> tuple[list[np.ndarray], dict]:
    """Both fingers closed by the elastic rod (right finger: handedness -1), and what to record."""
    bases = gripper_centrelines(GRIPPER_CENTER_MM, BASE_SEPARATION_MM, LENGTH_MM, 2)
    fingers, record = [], {}
    for side, base, hand in (("left", bases[0][0], 1.0), ("right", bases[1][0], -1.0)):
        closure = close_rod(base, THETA, LENGTH_MM, HALF_THICKNESS_MM, sdf, handedness=hand)
        if not bool(closure.converged):
            raise RuntimeError(f"the {side} rod closure did not converge: change the scene")
        fingers.append(np.asarray(closure.points, np.float64))
        record[side] = {
            "observed_joints_mm": np.round(np.asarray(observed_joints(closure, N_LINKS)), 4).tolist(),
            "max_penetration_mm": round(float(closure.max_penetration), 4),
            "touches": bool(np.any(np.asarray(closure.in_contact))),
        }
    return fingers, record


def _write(frame_scene: Scene, out: Path, name: str) -> None:
    target = out / name
    if target.exists():
        shutil.rmtree(target)  # only the folders this script makes
    save_frame(render(frame_scene, d405_intrinsics(WIDTH, HEIGHT)), target)


def make_samples(out: Path) -> dict:
    """Render every sample frame into ``out`` and return the ground truth (also written as truth.json)."""
    out.mkdir(parents=True, exist_ok=True)
    open_fingers = gripper_centrelines(GRIPPER_CENTER_MM, BASE_SEPARATION_MM, LENGTH_MM, 64)
    truth: dict = {
        "gripper": {"length_mm": LENGTH_MM, "half_thickness_mm": HALF_THICKNESS_MM, "theta_entire": THETA,
                    "base_separation_mm": BASE_SEPARATION_MM, "center_mm": list(GRIPPER_CENTER_MM),
                    "pose": [GRIPPER_CENTER_MM[0], GRIPPER_CENTER_MM[1], 0.0], "n_links": N_LINKS},
        "camera": {"plane_depth_mm": PLANE_DEPTH_MM, "intrinsics": d405_intrinsics(WIDTH, HEIGHT).to_dict()},
        "frames": {},
    }
    _write(_scene(open_fingers, None, CALIBRATION_SEEDS["calib_open"]), out, "calib_open")
    truth["frames"]["calib_open"] = {"closed": False, "object": None, "seed": CALIBRATION_SEEDS["calib_open"]}
    closed, record = _closed_fingers(None)
    _write(_scene(closed, None, CALIBRATION_SEEDS["calib_closed"]), out, "calib_closed")
    truth["frames"]["calib_closed"] = {"closed": True, "object": None, "seed": CALIBRATION_SEEDS["calib_closed"],
                                       "fingers": record}
    for sample in SCENES:
        polygon = sample.polygon()
        obj = {"shape": sample.name, "size_mm": sample.size_mm, "angle": sample.angle,
               "center_mm": list(sample.center_mm), "polygon_mm": np.round(polygon, 4).tolist()}
        _write(_scene(open_fingers, polygon, sample.seed), out, f"{sample.name}_open")
        truth["frames"][f"{sample.name}_open"] = {"closed": False, "object": obj, "seed": sample.seed}
        closed, record = _closed_fingers(PolygonSDF(np.asarray(polygon, np.float32)))
        _write(_scene(closed, polygon, sample.seed + 1), out, f"{sample.name}_closed")
        truth["frames"][f"{sample.name}_closed"] = {"closed": True, "object": obj, "seed": sample.seed + 1,
                                                    "fingers": record}
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return truth


def make_profile(out: Path) -> Path:
    """Calibrate from the calibration pair (one frame, eqs. 4-5) and save ``sample_profile.json``."""
    from softgrip_calib.one_frame import one_frame_from_frames
    from softgrip_calib.profile import save_profile

    profile = one_frame_from_frames(load_frame(out / "calib_closed"), load_frame(out / "calib_open"), N_LINKS,
                                    label="calib_open + calib_closed", camera_name="synthetic D405")
    path = save_profile(profile, out / "sample_profile.json")
    path.chmod(0o644)  # readable like the frames (the profile writer creates private files)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent,
                        help="folder to write into (default: this script's folder, data/)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    make_samples(args.out)
    profile = make_profile(args.out)
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(f"wrote {len(SCENES) * 2 + 2} frames, truth.json and {profile.name} into {args.out} "
          f"({size / 1e6:.1f} MB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
