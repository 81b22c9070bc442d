"""``softgrip estimate``: where each finger will touch and what shape it will take, for one or many frames."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

from softgrip_cli import _pipeline as pipe
from softgrip_cli._args import add_method_argument, resolve_estimator
from softgrip_cli._main import one_line
from softgrip_jax import SoftgripError, Status

EPILOG = """examples:
  softgrip estimate data/circle_open --profile data/sample_profile.json
  softgrip estimate data/*_open --profile data/sample_profile.json --json > estimates.json
  softgrip estimate data/*_open --profile data/sample_profile.json -o estimates.json
  softgrip estimate frames/frame_0003 --profile gripper.json --overlay-dir overlays

Each FRAME is a frame folder (color.png, depth.png, intrinsics.json) of the OPEN gripper, with the
object between the fingers. The gripper's pose is read from the frame (the midpoint of the finger
bases); the estimate says what the fingers will do when the gripper closes there.

With --json (or -o FILE), one JSON document (schema: softgrip_base/schemas/estimate.schema.json):
  {"format": "softgrip-estimate/1", "kind": "estimate", "units": {"length": "mm", "angle": "rad", "image": "px"},
   "conventions": {"units", "origin", "axes", "angle", "pose", "plane"}, "profile": {"path", "sha256",
   "camera", "fit_method", "estimate_method", "base_separation", "fingers"}, "method": ...,
   "frames": [FRAME, ...], "n_frames": K, "n_estimated": K, "n_failed": 0}
with one FRAME per frame folder, in the order given (--jsonl prints each FRAME on its own line instead):
  {"frame": PATH, "valid": bool, "status": "ok"|STATUS, "method": "geometric"|"mechanics", "n_links": N,
   "fingers": [{"side": "left"|"right", "valid": bool, "status": "ok"|STATUS,
   "case": "none"|"tip"|"tip_and_other"|"other", "theta_entire": rad,
   "joints_px": [[u, v], ...], "joints_mm": [[x, y], ...],
   "contacts_px": [[u, v], ...], "contacts_mm": [[x, y], ...]}, {...right...}],
   "pose": {"x_mm", "y_mm", "angle_rad"}, "plane": {"depth_mm", "normal", "tilt_deg"}}
Joints run from the base (index 0) to the tip (index N); contacts are the first contact P_o1 on the
object, and P_o2 too when the case is tip_and_other (none for case none). Millimetres are in the
gripper plane, pixels in the frame. Progress and diagnostics go to stderr. A frame is valid when
both fingers' estimates are; STATUS names why not (non_finite_input, base_outside_sdf, ...; see the
README's "Errors and exit codes"). With several frames, a frame that cannot be read is reported and
skipped (in the JSON as {"frame", "valid": false, "status": "error", "error": MESSAGE, ...}), the
others are estimated, and the command exits with 2 at the end naming the frames that failed.
Overlays (--overlay-dir): DIR/<frame-name>.png, estimated joints blue, contacts red.
"""

_STATUS_TEXT: dict[int, str] = {  # looked up by the status code
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
    formats = parser.add_mutually_exclusive_group()
    formats.add_argument("--json", action="store_true",
                        help="print one JSON document on stdout (softgrip_base/schemas/estimate.schema.json): units, "
                             "conventions, the profile, and a list of frames")
    formats.add_argument("--jsonl", action="store_true",
                        help="print one JSON object per frame and line (the format before the document; each "
                             "line is an element of the document's frames)")
    parser.add_argument("-o", "--output", metavar="FILE",
                        help="write the JSON document (as --json prints it) to FILE, atomically ('-': stdout)")
    parser.add_argument("--overlay-dir", metavar="DIR", help="write DIR/<frame-name>.png overlays")
    parser.add_argument("--length-from-frame", action="store_true",
                        help="use each finger's length measured in the frame instead of the profile's")
    pipe.add_force_argument(parser)
    add_method_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from softgrip_vision import documents
    from softgrip_base.atomic_write import atomic_open
    from softgrip_vision.overlay import save_png
    from softgrip_vision.scene import conventions

    profile = pipe.load_profile(args.profile)
    estimator = resolve_estimator(args.method, profile)
    method = estimator.name  # what the documents record
    settings = pipe.segmentation_settings(profile)
    overlay_dir = pipe.ensure_dir(args.overlay_dir, "overlay folder") if args.overlay_dir else None
    names = pipe.unique_png_names(args.frames)
    inputs = pipe.frame_inputs(*args.frames) + [Path(args.profile)]
    output = None if args.output in (None, "-") else args.output
    if output is not None:
        pipe.check_output_file(output, "-o", inputs, args.force)
    if overlay_dir is not None:  # before any work: no overlay may replace an input
        for name in names:
            pipe.check_output_file(overlay_dir / name, "overlay", inputs, args.force)
    to_stdout = args.json or args.output == "-"
    start = time.perf_counter()
    failed: list[str] = []
    header = {**documents.document_header("estimate", documents.profile_identity(profile, args.profile),
                                          conventions()), "method": method}
    with contextlib.ExitStack() as stack:
        writers = []
        if output is not None:
            handle = stack.enter_context(_file_errors(atomic_open(output, inputs=inputs, force=args.force, what="-o"),
                                                      output))
            writers.append(lambda text: handle.write(text.encode("utf-8")))
        if to_stdout and not args.jsonl:
            writers.append(_stdout_write)
        document = documents.DocumentWriter(lambda text: [w(text) for w in writers], header, "frames") \
            if writers else None

        def emit(record: dict) -> None:
            if document is not None:
                document.add(record)
            if args.jsonl:
                tqdm.write(json.dumps(record, allow_nan=False), file=sys.stdout)
                sys.stdout.flush()

        with tqdm(total=len(args.frames), desc="estimate", unit="frame", file=sys.stderr, disable=True if pipe.quiet() else None,
                  leave=False) as bar:
            for path, name in zip(args.frames, names):
                try:
                    scene = pipe.frame_scene(path, profile, length_from_frame=args.length_from_frame,
                                             settings=settings)
                except SoftgripError as err:
                    if len(args.frames) == 1:
                        raise
                    # One bad frame of many: say so, keep going, and fail at the end naming it.
                    failed.append(path)
                    print(f"softgrip estimate: error: {one_line(str(err))} (skipped; continuing with the other "
                          f"frames)", file=sys.stderr)
                    emit(pipe.failed_frame_json(path, method, str(err)))
                    bar.update()
                    continue
                grasp = pipe.estimate_scene(scene, estimator)
                for side in pipe.SIDES:
                    estimate = getattr(grasp, side)
                    if not bool(estimate.valid):
                        pipe.warn(f"{path}: the {side} finger's estimate is not valid: "
                                  f"{_STATUS_TEXT.get(int(estimate.status), pipe.status_name(estimate.status))}")
                record = pipe.frame_json(scene, grasp, method)
                pipe.info(scene.summary())
                emit(record)
                if not (to_stdout or args.jsonl):
                    tqdm.write(_table(scene, record), file=sys.stdout)
                    sys.stdout.flush()
                if overlay_dir is not None:
                    cases = ", ".join(f"{f['side']} {f['case']}" for f in record["fingers"])
                    image = pipe.grasp_overlay(scene.frame.color, grasp, scene.camera,
                                               label=f"{scene.name}: {cases}\nblue: estimated joints, red: contacts")
                    save_png(overlay_dir / name, image, inputs=inputs, force=args.force, what="overlay")
                bar.update()
        done = len(args.frames) - len(failed)
        if document is not None:
            document.close({"n_frames": len(args.frames), "n_estimated": done, "n_failed": len(failed)})
            if to_stdout:
                sys.stdout.flush()
    pipe.note(f"estimated {done} frame(s) in {time.perf_counter() - start:.1f} s")
    if failed:
        raise SoftgripError(f"{len(failed)} of {len(args.frames)} frames failed: {', '.join(failed)} (the other "
                            f"{done} were estimated; the reasons are above)")
    return 0


def _stdout_write(text: str) -> None:
    sys.stdout.write(text)


@contextlib.contextmanager
def _file_errors(context, path: str):
    """``context`` (an ``atomic_open``), with an OSError while writing reported as a SoftgripError
    naming ``-o`` and the file (which is left as it was)."""
    try:
        with context as handle:
            yield handle
    except OSError as err:
        raise SoftgripError(f"-o {path}: cannot write it ({err.strerror}); it is left as it was") from None


def _table(scene: pipe.FrameScene, record: dict) -> str:
    x, y, angle = scene.pose
    lines = [f"{one_line(scene.path)}: {record['method']} estimate, N = {record['n_links']}, "
             f"gripper at x {x:.1f} mm, y {y:.1f} mm, "
             f"angle {angle:.3f} rad"]
    for finger in record["fingers"]:
        tip = finger["joints_mm"][-1]
        tip_text = "-" if None in tip else f"({tip[0]:.1f}, {tip[1]:.1f})"
        contacts = "; ".join(f"({c[0]:.1f}, {c[1]:.1f})" for c in finger["contacts_mm"] if None not in c) or "-"
        lines.append(f"  {finger['side']:<6} {finger['case']:<14} contacts (mm) {contacts:<28} tip (mm) {tip_text}")
    return "\n".join(lines)
