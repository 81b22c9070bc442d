"""``softgrip demo``: the whole pipeline on the sample frames (no camera, no arguments).

The frames ship with the package (:func:`softgrip_vision.samples.sample_data_dir`: package data in
an installed wheel, the repository's ``data/`` in a source checkout).

Calibrate from the calibration pair (one frame, eqs. 4-5), estimate every scene from its open
frame and compare with the observed closure in its closed frame (eq. 10), score a default grid of
gripper poses on the first scene and refine the best one (a compass search), and write overlays,
the heat map, the calibrated profile and a JSON summary into the output folder.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from softgrip_cli import _pipeline as pipe
from softgrip_cli._args import add_method_argument, resolve_estimator
from softgrip_jax import SoftgripError, joint_errors
from softgrip_base.atomic_write import write_atomic
from softgrip_vision.samples import sample_data_dir

DATA_DIR = sample_data_dir()
CALIB_OPEN, CALIB_CLOSED = "calib_open", "calib_closed"
SAMPLE_PROFILE = "sample_profile.json"
DEFAULT_N_LINKS = 20

EPILOG = """examples:
  softgrip demo                      # writes into demo-out/ and prints a summary table
  softgrip demo --out /tmp/demo --json

The output folder gets (files of the same names are replaced, nothing else is touched):
  profile.json              the calibration made from data/calib_open + data/calib_closed
  estimate_<scene>.png      each scene's estimate: joints blue, contacts red, observed closure green
  heatmap_<scene>.png       score of every gripper-centre position on the first scene
  refined_<scene>.png       the best grid pose after refinement
  summary.json              everything above as numbers (also printed with --json)
"""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="calibrate, estimate, score and refine on the shipped sample frames", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the whole pipeline on the sample frames shipped with the package: calibrate from the "
                    "calibration pair, estimate each scene, score a grid of poses and refine the best.",
    )
    parser.add_argument("-o", "--output", "--out", dest="out", default="demo-out", metavar="DIR",
                        help="output folder (default: demo-out)")
    parser.add_argument("--data", default=None, metavar="DIR",
                        help=f"sample frames (default: the shipped ones, {DATA_DIR})")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")
    add_method_argument(parser, from_profile=False)  # its one-frame profile records no estimate
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    data = Path(args.data) if args.data else DATA_DIR
    scenes = _scene_names(data)
    if Path(os.path.realpath(args.out)).is_relative_to(os.path.realpath(data)):
        raise SoftgripError(f"--out {args.out} lies inside the sample frames' folder {data}, the demo's input: "
                            f"choose an output folder outside it")
    out = pipe.ensure_dir(args.out, "output folder")
    timings: dict[str, float] = {}
    written: list[str] = []

    t = time.perf_counter()
    profile, calibration = _calibrate(data, out)
    estimator = resolve_estimator(args.method, profile)
    written.append("profile.json")
    timings["calibrate"] = time.perf_counter() - t

    t = time.perf_counter()
    scene_objects = {name: pipe.frame_scene(data / f"{name}_open", profile) for name in scenes}
    refine_compiled = _compile_refine(scene_objects[scenes[0]], estimator)
    scene_results = []
    for name in scenes:
        result = _estimate_scene(data, name, scene_objects[name], profile, out, estimator)
        scene_results.append(result)
        written.append(result["overlay"])
    timings["estimate"] = time.perf_counter() - t

    t = time.perf_counter()
    scored = _score_scene(scene_objects[scenes[0]], out, estimator)
    written.append(scored["heatmap"])
    timings["score"] = time.perf_counter() - t

    t = time.perf_counter()
    refine_compiled.join()
    refined = _refine(scene_objects[scenes[0]], scored, out, estimator)
    written.append(refined["overlay"])
    timings["refine"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start

    summary = {"data": str(data), "out": str(out), "method": estimator.name, "calibration": calibration,
               "scenes": scene_results,
               "score": scored, "refine": refined, "timings_s": {k: round(v, 2) for k, v in timings.items()},
               "files": written + ["summary.json"]}
    _write_json(out / "summary.json", summary)
    if args.json:
        json.dump(summary, sys.stdout, allow_nan=False)
        print()
    else:
        print(_table(summary))
    sys.stdout.flush()
    pipe.note(f"demo finished in {timings['total']:.1f} s (including compilation; later runs reuse it)")
    return 0


# ---------------------------------------------------------------------------------------------
# Steps


def _scene_names(data: Path) -> list[str]:
    """Scene names with an open frame ``<name>_open`` in ``data`` (the calibration pair aside), sorted."""
    if not data.is_dir():
        raise SoftgripError(f"the sample frames folder {data} does not exist: pass --data DIR (a folder with "
                            f"calib_open/, calib_closed/ and <name>_open/ frames), or reinstall softgrip-jax")
    for needed in (CALIB_OPEN, CALIB_CLOSED):
        if not (data / needed).is_dir():
            raise SoftgripError(f"{data}: the calibration frame {needed}/ is missing; regenerate the samples "
                                f"with .venv/bin/python data/make_samples.py")
    names = sorted(p.name[:-len("_open")] for p in data.glob("*_open") if p.is_dir() and p.name != CALIB_OPEN)
    if not names:
        raise SoftgripError(f"{data}: no scene frames (<name>_open/); regenerate the samples with "
                            f".venv/bin/python data/make_samples.py")
    return names


def _calibrate(data: Path, out: Path):
    """One-frame calibration from the calibration pair (calib), or the shipped sample profile."""
    sample = data / SAMPLE_PROFILE
    sample_profile = pipe.load_profile(sample) if sample.is_file() else None
    try:
        from softgrip_calib.one_frame import one_frame_from_frames
        from softgrip_calib.profile import save_profile
    except ImportError:  # calibration not available: use the profile shipped with the samples
        if sample_profile is None:
            raise SoftgripError(f"{sample}: no sample profile, and calibration is not available") from None
        profile, source = sample_profile, str(sample)
        _write_json(out / "profile.json", profile.to_dict())
    else:
        from softgrip_vision.frames import load_frame

        n_links = sample_profile.fingers["left"].n_links if sample_profile else DEFAULT_N_LINKS
        settings = pipe.segmentation_settings(sample_profile) if sample_profile else None
        try:
            profile = one_frame_from_frames(load_frame(data / CALIB_CLOSED), load_frame(data / CALIB_OPEN), n_links,
                                            settings, label=f"{CALIB_OPEN} + {CALIB_CLOSED}",
                                            camera_name="synthetic D405")
        except SoftgripError as err:
            raise SoftgripError(f"calibrating from {data / CALIB_CLOSED} and {data / CALIB_OPEN}: {err}") from None
        save_profile(profile, out / "profile.json")
        source = f"{data / CALIB_OPEN} + {data / CALIB_CLOSED} (one frame, eqs. 4-5)"
    fingers = {side: {"length_mm": round(profile.fingers[side].length, 3),
                      "theta_entire": round(profile.fingers[side].theta_entire, 5),
                      "half_thickness_mm": round(profile.fingers[side].half_thickness, 3)} for side in pipe.SIDES}
    residual = profile.fit.residual_rms_mm
    return profile, {"source": source, "profile": "profile.json", "n_links": profile.fingers["left"].n_links,
                     "base_separation_mm": round(profile.base_separation, 3), "fingers": fingers,
                     "residual_rms_mm": None if residual is None else round(residual, 4)}


def _compile_refine(scene: pipe.FrameScene, estimator) -> threading.Thread:
    """Start compiling ``refine`` for ``scene``'s shapes in a background thread, and return it.

    Refine's program is the demo's largest compile; it depends only on shapes and settings, not on
    which pose is refined, so it is compiled (by refining the frame's own pose, result discarded)
    while the scenes are estimated and the grid is scored, on the other core. Join the thread before
    refining: the call then finds the program compiled. A failure here is left to that call to
    report. A daemon thread: an interrupted demo does not wait for the compiler."""
    import jax.numpy as jnp

    from softgrip_jax import refine

    def compile_by_refining() -> None:
        try:
            refine(scene.gripper, scene.sdf, jnp.asarray(scene.pose, scene.gripper.base_separation.dtype),
                   estimator=estimator)
        except Exception:  # noqa: BLE001 - the demo's own refine call raises it again, in the main thread
            pass

    thread = threading.Thread(target=compile_by_refining, name="softgrip-refine-compile", daemon=True)
    thread.start()
    return thread


def _estimate_scene(data: Path, name: str, scene: pipe.FrameScene, profile, out: Path, estimator) -> dict:
    """Estimate one scene at its frame's pose with ``estimator``; compare with its observed closure
    when present."""
    from softgrip_vision.overlay import save_png

    grasp = pipe.estimate_scene(scene, estimator)
    record = pipe.frame_json(scene, grasp, estimator.name)
    result = {"scene": name, "frame": record["frame"], "pose": pipe.pose_json(scene.pose),
              "valid": bool(grasp.valid), "n_links": record["n_links"], "fingers": record["fingers"]}
    observed_px, errors = [], None
    closed_path = data / f"{name}_closed"
    if closed_path.is_dir():
        observed = _observed(closed_path, profile, scene.n_links)
        observed_px = [scene.camera.mm_to_px(points) for points in observed]
        n = scene.n_links
        errors = {}
        for side, points in zip(pipe.SIDES, observed):
            dist = np.asarray(joint_errors(getattr(grasp, side).joints, points), np.float64)  # eq. 10
            errors[side] = {"mid_mm": pipe.number_json(dist[n // 2], 3), "tip_mm": pipe.number_json(dist[n], 3),
                            "mean_mm": pipe.number_json(dist.mean(), 3)}
        result["observed_frame"] = str(closed_path)
    result["errors_vs_observed"] = errors
    cases = ", ".join(f"{f['side']} {f['case']}" for f in record["fingers"])
    legend = "blue: estimated joints, red: contacts" + (", green: observed closure" if observed_px else "")
    image = pipe.grasp_overlay(scene.frame.color, grasp, scene.camera, observed_px,
                               label=f"{name}: {cases}\n{legend}")
    result["overlay"] = f"estimate_{name}.png"
    save_png(out / result["overlay"], image)
    return result


def _observed(path: Path, profile, n_links: int) -> list[np.ndarray]:
    """[left, right] observed positions (eq. 10: the closed centreline in N equal arc lengths), mm."""
    from softgrip_vision.frames import load_frame, undistort_frame
    from softgrip_vision.measure import measure_gripper
    from softgrip_vision.segmentation import segment

    try:
        frame = undistort_frame(load_frame(path))
        seg = segment(frame, pipe.segmentation_settings(profile))
        keypoints = measure_gripper(frame, seg, profile.measure_settings()).keypoints
    except SoftgripError as err:
        raise SoftgripError(f"{path}: {err}") from None
    return [k.observed_mm(n_links) for k in keypoints]


def _score_scene(scene: pipe.FrameScene, out: Path, estimator) -> dict:
    """Score the default grid on ``scene`` with ``estimator`` and write its heat map."""
    from softgrip_cli import cmd_score
    from softgrip_vision.overlay import save_png

    grid = cmd_score.default_grid(scene)
    poses = cmd_score.grid_poses(*grid)
    result, elapsed = cmd_score.score_poses(scene, poses, estimator)
    order = cmd_score.rank(result)
    best = int(order[0])
    name = scene.name[:-len("_open")] if scene.name.endswith("_open") else scene.name
    heatmap = f"heatmap_{name}.png"
    from softgrip_vision import plots

    try:
        plots.require_matplotlib()
    except SoftgripError:  # no matplotlib: the OpenCV drawing on the frame's pixels
        pipe.note(f"{heatmap} drawn without mm axes: for the plot, {plots.INSTALL_HINT}")
        save_png(out / heatmap, cmd_score.heatmap_image(scene, poses, result, grid, best))
    else:
        plots.save_figure(plots.heatmap_figure(scene, poses, result, grid, best), out / heatmap)
    return {
        "scene": name, "n_candidates": len(poses), "n_valid": int(np.sum(result.valid)),
        "seconds": round(elapsed, 3),
        "grid": {"x_mm": [round(float(grid[0][0]), 3), round(float(grid[0][-1]), 3), len(grid[0])],
                 "y_mm": [round(float(grid[1][0]), 3), round(float(grid[1][-1]), 3), len(grid[1])],
                 "angle_rad": [round(float(grid[2][0]), 4), round(float(grid[2][-1]), 4), len(grid[2])]},
        "best": pipe.candidate_json(poses[best], pipe.take(result, best), scene.gripper, scene.camera),
        "top": [pipe.candidate_json(poses[i], pipe.take(result, int(i)), scene.gripper, scene.camera)
                for i in order[1:5]],
        "heatmap": heatmap,
    }


def _refine(scene: pipe.FrameScene, scored: dict, out: Path, estimator) -> dict:
    """Refine the best grid pose (softgrip_jax.refine with ``estimator``) and draw the result."""
    import jax.numpy as jnp

    from softgrip_jax import RefineStatus, refine
    from softgrip_vision.overlay import save_png

    best = scored["best"]["pose"]
    start_pose = np.array([best["x_mm"], best["y_mm"], best["angle_rad"]])
    refined = pipe.to_numpy(refine(scene.gripper, scene.sdf,
                                   jnp.asarray(start_pose, scene.gripper.base_separation.dtype), estimator=estimator))
    pose = np.asarray(refined.pose, np.float64)
    status = RefineStatus(int(refined.status)).name.lower()
    candidate = pipe.candidate_json(pose, refined.score, scene.gripper, scene.camera)
    overlay = f"refined_{scored['scene']}.png"
    cases = ", ".join(f"{f['side']} {f['case']}" for f in candidate["fingers"])
    label = (f"{scored['scene']}: refined pose x {pose[0]:.1f} mm, y {pose[1]:.1f} mm, angle {pose[2]:.2f} rad\n"
             f"score {pipe.number_json(refined.start_score, 3)} -> {pipe.number_json(refined.score.score, 3)} "
             f"({status}); {cases}\nblue: estimated joints, red: contacts")
    save_png(out / overlay, pipe.grasp_overlay(scene.frame.color, refined.score.grasp, scene.camera, label=label))
    return {"scene": scored["scene"], "start_pose": pipe.pose_json(start_pose),
            "start_score": pipe.number_json(refined.start_score), "pose": pipe.pose_json(pose),
            "score": candidate["score"], "status": status, "steps": int(refined.steps),
            "solver_result": int(refined.solver_result), "candidate": candidate, "overlay": overlay}


# ---------------------------------------------------------------------------------------------
# Output


def _write_json(path: Path, data: dict) -> None:
    try:
        write_atomic(path, (json.dumps(data, indent=1, allow_nan=False) + "\n").encode("utf-8"))
    except OSError as err:
        raise SoftgripError(f"could not write {path}: {err.strerror}; check that its folder exists and is "
                            f"writable") from None


def _fmt(value, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def _table(summary: dict) -> str:
    cal = summary["calibration"]
    left, right = cal["fingers"]["left"], cal["fingers"]["right"]
    lines = [
        f"softgrip demo: {len(summary['scenes'])} scenes from {summary['data']}, output in {summary['out']}/, "
        f"{summary['method']} estimate",
        f"calibration (one frame pair, eqs. 4-5): Theta {left['theta_entire']:.3f} / {right['theta_entire']:.3f} rad, "
        f"L {left['length_mm']:.1f} / {right['length_mm']:.1f} mm, W {cal['base_separation_mm']:.1f} mm, "
        f"N = {cal['n_links']}, residual {_fmt(cal['residual_rms_mm'])} mm",
        "",
        f"{'scene':<10} {'finger':<6} {'case':<14} {'first contact (mm)':<20} {'error at N/2':>12} {'error at tip':>12}",
    ]
    for scene in summary["scenes"]:
        for finger in scene["fingers"]:
            contact = finger["contacts_mm"][0] if finger["contacts_mm"] else None
            contact_text = "-" if contact is None or None in contact else f"({contact[0]:.1f}, {contact[1]:.1f})"
            errors = (scene["errors_vs_observed"] or {}).get(finger["side"], {})
            lines.append(f"{scene['scene']:<10} {finger['side']:<6} {finger['case']:<14} {contact_text:<20} "
                         f"{_fmt(errors.get('mid_mm')) + ' mm':>12} {_fmt(errors.get('tip_mm')) + ' mm':>12}")
    score, ref = summary["score"], summary["refine"]
    best = score["best"]
    if summary["method"] == "geometric":
        lines += ["(errors: eq. 10, estimate vs the observed closure of the closed frame; the paper's cases (b) "
                  "and (c)", " pivot the finger about its base, so they miss a clamped finger's tip by millimetres)"]
    else:
        lines += ["(errors: eq. 10, estimate vs the observed closure of the closed frame)"]
    lines += [
        "",
        f"score ({score['scene']}): {score['n_candidates']} poses in {score['seconds']:.2f} s, {score['n_valid']} valid; "
        f"best x {best['pose']['x_mm']:.1f} mm, y {best['pose']['y_mm']:.1f} mm, "
        f"angle {best['pose']['angle_rad']:.2f} rad, score {_fmt(best['score'], '.3f')}",
        f"refine: x {ref['pose']['x_mm']:.1f} mm, y {ref['pose']['y_mm']:.1f} mm, angle {ref['pose']['angle_rad']:.2f} "
        f"rad, score {_fmt(ref['start_score'], '.3f')} -> {_fmt(ref['score'], '.3f')} ({ref['status']}, "
        f"{ref['steps']} steps)",
        "",
        "wrote " + ", ".join(summary["files"]) + f" into {summary['out']}/",
    ]
    return "\n".join(lines)
