"""``softgrip estimate``: where each finger will touch and what shape it will take, for one or many frames."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from softgrip_cli import _pipeline as pipe
from softgrip_cli._args import add_method_argument, resolve_method
from softgrip_cli._main import one_line
from softgrip_jax import SoftgripError, Status

EPILOG = """examples:
  softgrip estimate data/circle_open --profile data/sample_profile.json
  softgrip estimate data/*_open --profile data/sample_profile.json --json > estimates.jsonl
  softgrip estimate frames/frame_0003 --profile gripper.json --overlay-dir overlays

Each FRAME is a frame folder (color.png, depth.png, intrinsics.json) of the OPEN gripper, with the
object between the fingers. The gripper's pose is read from the frame (the midpoint of the finger
bases); the estimate says what the fingers will do when the gripper closes there.

With --json, stdout has one JSON object per frame, one per line, in the order given:
  {"frame": PATH, "valid": bool, "status": "ok"|STATUS, "method": "geometric"|"mechanics", "n_links": N,
   "fingers": [{"side": "left"|"right", "valid": bool, "status": "ok"|STATUS,
   "case": "none"|"tip"|"tip_and_other"|"other", "theta_entire": rad,
   "joints_px": [[u, v], ...], "joints_mm": [[x, y], ...],
   "contacts_px": [[u, v], ...], "contacts_mm": [[x, y], ...]}, {...right...}]}
Joints run from the base (index 0) to the tip (index N); contacts are the first contact P_o1 on the
object, and P_o2 too when the case is tip_and_other (none for case none). Millimetres are in the
gripper plane, pixels in the frame. Progress and diagnostics go to stderr. A frame is valid when
both fingers' estimates are; STATUS names why not (non_finite_input, base_outside_sdf, ...; see the
README's "Errors and exit codes"). With several frames, a frame that cannot be read is reported and
skipped (with --json as {"frame", "valid": false, "status": "error", "error": MESSAGE, ...}), the
others are estimated, and the command exits with 2 at the end naming the frames that failed.
Overlays (--overlay-dir): DIR/<frame-name>.png, estimated joints blue, contacts red.
"""

_STATUS_TEXT = {
    Status.NON_FINITE_INPUT: "a non-finite base or calibration value",
    Status.BASE_OUTSIDE_SDF: "its base lies outside the image",
    Status.INITIAL_OVERLAP: "the object already overlaps the open finger (is the object touching it?)",
    Status.ROOT_NOT_CONVERGED: "the contact search did not converge",
    Status.NON_FINITE_SDF: "the object's distance grid holds NaN or inf values",
    Status.PARAMETER_OUT_OF_RANGE: "a calibration value is out of its range (Theta, L, r, ...)",
    Status.COORDINATE_OUT_OF_RANGE: "its base lies farther than 100 m away (a unit mistake?)",
    Status.NON_FINITE_RESULT: "the estimate came out NaN or inf",
}


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "estimate", help="contact case, contact points and joints of each finger of one or many frames",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Estimate, before anything is touched, where each finger of the gripper in each "
                    "FRAME will touch the object when it closes and what shape it will take.",
    )
    parser.add_argument("frames", nargs="+", metavar="FRAME", help="frame folder(s) of the open gripper")
    parser.add_argument("--profile", required=True, metavar="P", help="calibration profile (JSON)")
    parser.add_argument("--json", action="store_true", help="one JSON object per frame and line on stdout")
    parser.add_argument("--overlay-dir", metavar="DIR", help="write DIR/<frame-name>.png overlays")
    parser.add_argument("--length-from-frame", action="store_true",
                        help="use each finger's length measured in the frame instead of the profile's")
    pipe.add_force_argument(parser)
    add_method_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from vision.overlay import save_png

    profile = pipe.load_profile(args.profile)
    method = resolve_method(args.method, profile)
    settings = pipe.segmentation_settings(profile)
    overlay_dir = pipe.ensure_dir(args.overlay_dir, "overlay folder") if args.overlay_dir else None
    names = pipe.unique_png_names(args.frames)
    inputs = pipe.frame_inputs(*args.frames) + [Path(args.profile)]
    if overlay_dir is not None:  # before any work: no overlay may replace an input
        for name in names:
            pipe.check_output_file(overlay_dir / name, "overlay", inputs, args.force)
    start = time.perf_counter()
    failed: list[str] = []
    with tqdm(total=len(args.frames), desc="estimate", unit="frame", file=sys.stderr, disable=None,
              leave=False) as bar:
        for path, name in zip(args.frames, names):
            try:
                scene = pipe.frame_scene(path, profile, length_from_frame=args.length_from_frame, settings=settings)
            except SoftgripError as err:
                if len(args.frames) == 1:
                    raise
                # One bad frame of many: say so, keep going, and fail at the end naming it.
                failed.append(path)
                print(f"softgrip estimate: error: {one_line(str(err))} (skipped; continuing with the other frames)",
                      file=sys.stderr)
                if args.json:
                    tqdm.write(json.dumps(pipe.failed_frame_json(path, method, str(err))), file=sys.stdout)
                    sys.stdout.flush()
                bar.update()
                continue
            grasp = pipe.estimate_scene(scene, method)
            for side in pipe.SIDES:
                estimate = getattr(grasp, side)
                if not bool(estimate.valid):
                    pipe.warn(f"{path}: the {side} finger's estimate is not valid: "
                              f"{_STATUS_TEXT.get(int(estimate.status), pipe.status_name(estimate.status))}")
            record = pipe.frame_json(scene, grasp, method)
            text = json.dumps(record, allow_nan=False) if args.json else _table(scene, record)
            tqdm.write(text, file=sys.stdout)
            sys.stdout.flush()
            if overlay_dir is not None:
                cases = ", ".join(f"{f['side']} {f['case']}" for f in record["fingers"])
                image = pipe.grasp_overlay(scene.frame.color, grasp, scene.camera,
                                           label=f"{scene.name}: {cases}\nblue: estimated joints, red: contacts")
                save_png(overlay_dir / name, image, inputs=inputs, force=args.force, what="overlay")
            bar.update()
    done = len(args.frames) - len(failed)
    print(f"estimated {done} frame(s) in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if failed:
        raise SoftgripError(f"{len(failed)} of {len(args.frames)} frames failed: {', '.join(failed)} (the other "
                            f"{done} were estimated; the reasons are above)")
    return 0


def _table(scene: pipe.FrameScene, record: dict) -> str:
    x, y, angle = scene.pose
    lines = [f"{scene.path}: {record['method']} estimate, N = {record['n_links']}, "
             f"gripper at x {x:.1f} mm, y {y:.1f} mm, "
             f"angle {angle:.3f} rad"]
    for finger in record["fingers"]:
        tip = finger["joints_mm"][-1]
        tip_text = "-" if None in tip else f"({tip[0]:.1f}, {tip[1]:.1f})"
        contacts = "; ".join(f"({c[0]:.1f}, {c[1]:.1f})" for c in finger["contacts_mm"] if None not in c) or "-"
        lines.append(f"  {finger['side']:<6} {finger['case']:<14} contacts (mm) {contacts:<28} tip (mm) {tip_text}")
    return "\n".join(lines)
