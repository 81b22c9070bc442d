"""``softgrip score``: score and rank many candidate gripper poses on one frame, with a heat map."""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from softgrip_cli import _pipeline as pipe
from softgrip_cli._args import add_method_argument, resolve_estimator
from softgrip_jax import SoftgripError, finger_frames
from softgrip_jax._quality import DEFAULT_MU
from softgrip_vision import documents
from softgrip_vision import scene as scene_api
from softgrip_vision.plots import TOP_GRASPS
from softgrip_base import input_guard, user_json
from softgrip_base.input_guard import one_line

EPILOG = """examples:
  softgrip score data/circle_open --profile data/sample_profile.json --heatmap heat.png
  softgrip score data/circle_open --profile data/sample_profile.json --grid=-20:20:41,-75:-40:36,-0.2:0.2:5 --json
  softgrip score data/circle_open --profile data/sample_profile.json --poses poses.csv --top 5
  softgrip score data/circle_open --profile data/sample_profile.json --mu 0.8 --grasps grasps.png

A pose is (x mm, y mm, angle rad): the point midway between the finger bases, in the gripper plane's
millimetres (the frame of `softgrip estimate`'s joints_mm), and the gripper's in-plane rotation
(0: fingers hanging straight down the image). Give --grid with '=' when it starts with a minus sign.

Poses:
  (default)   a grid around the object: x over its extent +-10 mm, y from one finger length above
              its top down to its top, the frame's gripper angle and +-0.2 rad (25 x 21 x 3 poses)
  --grid      X0:X1:NX,Y0:Y1:NY,A0:A1:NA  (inclusive ranges: NX values from X0 to X1, ...)
  --poses     FILE.json: [[x, y, angle], ...], [{"x_mm", "y_mm", "angle_rad"}, ...], {"poses": [...]}
              or this command's own --json output; FILE.csv: rows x_mm,y_mm[,angle_rad], optional
              header naming the columns; angle 0 when left out. Values separated by ',', ';' or tab
              (as spreadsheets save CSV; a UTF-8 byte-order mark is fine); a decimal comma (0,5) is
              refused: save with a decimal point

With --json (or -o FILE), one JSON document (schema: softgrip_base/schemas/score.schema.json): {"format":
"softgrip-score/2", "kind": "score", "units", "conventions" (origin, axes, units, the gripper plane's
depth_mm, normal and tilt_deg), "profile" (path, sha256, camera, fit, geometry), "frame", "method",
"friction": {"mu"}, "n_links", "n_candidates", "n_valid", "frame_pose" (the gripper's pose read from
the frame), "candidates": [...]}, the candidates ranked best first (--top K of them, 0 for all), each
{"pose": {"x_mm", "y_mm", "angle_rad"}, "score" (null when not valid), "quality" (Ferrari-Canny L1
epsilon with friction mu; 0 without force closure, null when not valid), "force_closure",
"centroid_mm" and "rho_mm" (the object's centroid and size: torques are about the centroid, over rho),
"components", "valid", "status", "fingers": [left, right]} with the fingers' fields as in `softgrip
estimate --json`, except that "contacts_mm" (and "contacts_px") are the quality's contacts, with the
parallel lists "normals" (the object's outward unit normals) and "forces" (on the object, in EI/L^2:
the finger's mean bending stiffness over its length squared; null for the geometric estimate).
The score: 1 + quality (1 - risk) in force closure, else 0.99 progress (1 - risk): every grasp in
force closure ranks above every grasp without.
The heat map (--heatmap IMAGE; .png, .jpg, .pdf, .svg, ... as the extension says; needs matplotlib:
pip install softgrip-jax[plots]) shows the frame in the gripper plane's mm, each gripper-centre
position coloured by its best quality over the angles (light grey: valid but no force closure, dark
grey: none valid), a colour bar, the whole grid in view, and the best pose's estimate (fingers blue,
contacts red, centre and base line black). The grasps picture (--grasps IMAGE, as --heatmap) shows
the top 5 valid candidates' estimated fingers and, at each contact, its friction cone (the two edges
at atan(mu) about the inward normal) and the contact force (mechanics estimate).
"""

#: Poses of the default grid along x, y and the angle (fixed, so every frame reuses one compilation).
DEFAULT_GRID_SHAPE = (25, 21, 3)
DEFAULT_MARGIN_MM = 10.0
DEFAULT_ANGLES = (-0.2, 0.0, 0.2)
MAX_POSES = 1_000_000
#: The range --mu accepts (``softgrip_jax.ScoreWeights.mu``'s).
MU_RANGE = (0.0, 10.0)
#: Defaults of the robust options: the arm's pose error (mm, rad), mu's relative spread, the outline's
#: error (mm; about half a pixel at the paper's working distance).
ROBUST_DEFAULTS: dict[str, Any] = {"pose": "0.5,0.01", "mu_spread": 0.2, "contour": 0.2}
_GRID_FORMAT = "X0:X1:NX,Y0:Y1:NY,A0:A1:NA (mm, mm, rad; e.g. -20:20:21,-80:-40:21,-0.2:0.2:3)"


class PoseInputError(SoftgripError):
    """A grid or a pose file that cannot be read; the message names it (and the line)."""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "score", help="score and rank candidate gripper poses on a frame, with a heat map",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Estimate both fingers at many candidate gripper poses on one frame in one compiled, "
                    "batched call, score each and rank them best first.",
    )
    parser.add_argument("frame", metavar="FRAME", help="frame folder with the object")
    parser.add_argument("--profile", required=True, metavar="P", help="calibration profile (JSON)")
    poses = parser.add_mutually_exclusive_group()
    poses.add_argument("--grid", metavar="X0:X1:NX,Y0:Y1:NY,A0:A1:NA", help="a grid of poses (mm, mm, rad)")
    poses.add_argument("--poses", metavar="FILE", help="poses from a .json or .csv file ('-': standard input, JSON "
                                                       "or CSV told apart by the first character)")
    parser.add_argument("--json", action="store_true", help="print the ranked candidates as JSON")
    parser.add_argument("--heatmap", metavar="IMAGE",
                        help="write the score heat map over the frame, in mm with a colour bar (matplotlib); the "
                             "format from the extension: .png, .jpg, .pdf, .svg, ...")
    parser.add_argument("--grasps", metavar="IMAGE",
                        help=f"write a picture of the top {TOP_GRASPS} valid grasps: their estimated fingers, each "
                             "contact's friction cone and force (matplotlib); the format from the extension, as "
                             "--heatmap")
    parser.add_argument("--mu", metavar="MU", default=None,
                        help=f"Coulomb friction coefficient between finger and object, from 0 to 10, for the grasp "
                             f"quality (default {DEFAULT_MU}: silicone on common dry objects)")
    robust = parser.add_argument_group(
        "robust quality", "score each candidate also for K draws of what is uncertain (the same draws for every "
                          "candidate): the profile's calibration standard errors (calibrate --fit writes them), the "
                          "arm's pose error, mu and the object's outline; ranks grasps in force closure by their "
                          "expected quality and reports quality_mean and p_closure (K times the time); or, with "
                          "--robust linear, a first-order expansion of the closure margin in all of them (one "
                          "derivative per uncertain input, no draws)")
    robust.add_argument("--robust", default="0", metavar="K|linear",
                        help="draws per candidate (e.g. 16), or 'linear' for the linearisation (default 0: the "
                             "nominal quality only)")
    robust.add_argument("--pose-sigma", default=None, metavar="MM,RAD",
                        help=f"the arm's pose error, standard deviations (default {ROBUST_DEFAULTS['pose']})")
    robust.add_argument("--mu-spread", default=None, metavar="S",
                        help=f"mu drawn uniformly from mu (1 +- S), S in [0, 1) (default {ROBUST_DEFAULTS['mu_spread']})")
    robust.add_argument("--contour-sigma", default=None, metavar="MM",
                        help=f"the object's outline grown or shrunk, standard deviation in mm (default "
                             f"{ROBUST_DEFAULTS['contour']})")
    parser.add_argument("-o", "--output", metavar="FILE",
                        help="write the ranked candidates as JSON (as --json prints them) to FILE, atomically: "
                             "a run that is stopped leaves FILE as it was ('-': stdout)")
    pipe.add_force_argument(parser)
    parser.add_argument("--top", type=int, default=10, metavar="K",
                        help="how many of the best candidates to print (default 10; 0 for all)")
    parser.add_argument("--length-from-frame", action="store_true",
                        help="use each finger's length measured in the frame instead of the profile's")
    add_method_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrip_vision import plots

    if args.top < 0:
        raise SoftgripError(f"--top must be >= 0 (0 prints every candidate), got {args.top}")
    mu = parse_mu(args.mu)
    profile = pipe.load_profile(args.profile)
    uncertainty_settings = parse_robust(args)
    estimator = resolve_estimator(args.method, profile)
    method = estimator.name  # what the documents record
    grid = None
    if args.poses:
        poses = read_poses(args.poses)  # before the frame: a bad file fails fast
    elif args.grid:
        grid = parse_grid(args.grid)
    inputs = pipe.frame_inputs(args.frame) + [Path(args.profile)] + ([Path(args.poses)] if args.poses not in
                                                                       (None, "-") else [])
    to_stdout = args.json or args.output == "-"
    output = None if args.output in (None, "-") else args.output
    figures = {flag: path for flag, path in (("--heatmap", args.heatmap), ("--grasps", args.grasps)) if path}
    for flag, path in figures.items():
        pipe.ensure_dir(Path(path).parent, f"{flag} folder")
        pipe.check_output_file(path, flag, inputs, args.force)
        plots.figure_format(path, flag)  # matplotlib installed, a format it writes
    if output:
        pipe.check_output_file(output, "-o", inputs, args.force)
    check_distinct_outputs({**({"-o": output} if output else {}), **figures})
    scene = pipe.frame_scene(args.frame, profile, length_from_frame=args.length_from_frame)
    if args.poses or args.grid:  # the user's numbers: in the units the command reads?
        check_pose_units(poses if grid is None else grid_poses(*grid), scene,
                         args.poses if args.poses else f"--grid {args.grid}")
    if not args.poses:
        grid = grid or default_grid(scene)
        poses = grid_poses(*grid)
    if not scene.has_object:
        pipe.warn(f"{args.frame}: no object found; every candidate closes on nothing (case none)")

    uncertainty = None
    if uncertainty_settings is not None:
        from softgrip_jax import Uncertainty

        uncertainty = Uncertainty.from_fit(profile.fit.standard_errors, scene.gripper, **uncertainty_settings)
    result, elapsed = score_poses(scene, poses, estimator, mu=mu, uncertainty=uncertainty)
    order = rank(result)
    n_valid = int(np.sum(result.valid))
    pipe.note(f"scored {len(poses)} candidate poses ({method} estimate) in {elapsed:.1f} s (including compilation "
              f"the first time); {n_valid} valid")

    shown = order if args.top == 0 else order[:args.top]
    if args.heatmap:
        figure = plots.heatmap_figure(scene, poses, result, grid, int(order[0]), mu=mu, robust=uncertainty is not None)
        plots.save_figure(figure, args.heatmap, inputs=inputs, force=args.force, what="--heatmap")
    if args.grasps:
        figure = plots.grasps_figure(scene, poses, result, order, mu=mu)
        plots.save_figure(figure, args.grasps, inputs=inputs, force=args.force, what="--grasps", tight=False)
    header = {**documents.document_header("score", documents.profile_identity(profile, args.profile),
                                          scene.conventions),
              "frame": scene.path, "method": method, "friction": documents.friction_json(mu),
              **({"robust": documents.uncertainty_json(uncertainty)} if uncertainty is not None else {}),
              "n_links": scene.n_links, "n_candidates": len(poses),
              "n_valid": n_valid, "frame_pose": documents.pose_json(scene.pose)}
    if output:
        from softgrip_base.atomic_write import atomic_open

        try:
            with atomic_open(output, inputs=inputs, force=args.force, what="-o") as handle:
                write_json_stream(lambda text: handle.write(text.encode("utf-8")), header, scene, poses, result,
                                  shown, robust=uncertainty is not None)
        except OSError as err:
            raise SoftgripError(f"-o {output}: cannot write it ({err.strerror}); it is left as it was") from None
    if to_stdout:
        write_json_stream(sys.stdout.write, header, scene, poses, result, shown, robust=uncertainty is not None)
        sys.stdout.flush()
    else:
        print(_table(scene, poses, result, shown, n_valid, robust=uncertainty is not None))
    return 0


#: Positions (mm) within this of the origin may be metres: a gripper within a metre of the camera's axis.
METRES_LIKE_MM = 1.0


def check_pose_units(poses: np.ndarray, scene: pipe.FrameScene, source: str) -> None:
    """Refuse poses (B, 3) that look like another unit than (mm, mm, rad), naming ``source`` (the
    file or the flag), the pose and the fix.

    - Degrees: an angle beyond pi in magnitude (a turn is 2 pi rad; in degrees, 10 means 0.1745).
    - Metres: a position within :data:`METRES_LIKE_MM` of the origin (and not the origin itself),
      where the gripper, read in mm, does not reach the object but, read in metres (times 1000),
      does. The gripper reaches the object when part of the object lies in the rectangle its
      fingers sweep (between the bases and one finger length below them, the bases' separation
      wide, plus the finger's thickness). A pose near the origin stays legal whenever the object
      is there (it is in reach), and the origin itself is the same in both units.

    Poses are in the gripper plane's millimetres, whose origin is where the camera's optical axis
    meets the plane (not the object): an object seen off the image centre lies tens of mm from it.

    Raises:
        PoseInputError: the first pose in another unit.
    """
    poses = np.asarray(poses, np.float64)
    angles = poses[:, 2]
    beyond = np.flatnonzero(np.abs(angles) > math.pi)
    if beyond.size:
        i = int(beyond[0])
        raise PoseInputError(f"{source}, pose {i + 1}: angle_rad is radians: {angles[i]:g} looks like degrees, "
                             f"use {math.radians(angles[i]):.4g} (radians = degrees x pi / 180)")
    if not scene.has_object:
        return
    radius = np.hypot(poses[:, 0], poses[:, 1])
    near = np.flatnonzero((radius > 0.0) & (radius <= METRES_LIKE_MM))
    if not near.size:
        return
    contours, _ = cv2.findContours(scene.segmentation.object.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    outline = scene.camera.px_to_mm(np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64))
    gripper = scene.gripper
    length = float(max(gripper.left.length, gripper.right.length))
    thickness = float(max(gripper.left.half_thickness, gripper.right.half_thickness))
    half_width = 0.5 * float(gripper.base_separation) + thickness

    def reaches(xy: np.ndarray, angle: float) -> bool:
        down = np.array([math.sin(angle), math.cos(angle)])
        across = np.array([down[1], -down[0]])
        d = outline - xy
        along, side = d @ down, d @ across
        return bool(np.any((np.abs(side) <= half_width) & (along >= -thickness) & (along <= length + thickness)))

    for i in near.tolist():
        xy, angle = poses[i, :2], float(poses[i, 2])
        if not reaches(xy, angle) and reaches(1000.0 * xy, angle):
            x, y = (float(v) for v in xy)
            raise PoseInputError(f"{source}, pose {i + 1}: the position ({x:g}, {y:g}) looks like metres: x_mm and "
                                 f"y_mm are millimetres (in mm the gripper is {float(radius[i]):.3g} mm from the "
                                 f"origin and does not reach the object; in metres it would): use "
                                 f"({1000 * x:g}, {1000 * y:g})")


def _number(text, flag: str, low: float, high: float, high_open: bool = False) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = math.nan
    ok = math.isfinite(value) and low <= value and (value < high if high_open else value <= high)
    if not ok:
        raise SoftgripError(f"{flag} {text}: expected a number from {low:g} to {high:g}"
                            f"{' (excluded)' if high_open else ''}")
    return value


def parse_robust(args: argparse.Namespace) -> dict | None:
    """The :class:`softgrip_jax.Uncertainty` settings of ``--robust K`` and its options (None: off);
    a SoftgripError naming the option otherwise. The options without ``--robust`` are refused."""
    given = [flag for flag, value in (("--pose-sigma", args.pose_sigma), ("--mu-spread", args.mu_spread),
                                      ("--contour-sigma", args.contour_sigma)) if value is not None]
    text = str(args.robust).strip()
    linear = text.lower() == "linear"
    try:
        samples = 0 if linear else int(text)
    except ValueError:
        samples = -1
    if not linear and samples == 0:
        if given:
            raise SoftgripError(f"{given[0]} sets robust scoring: add --robust K (e.g. --robust 16) or --robust linear")
        return None
    if not linear and not 1 <= samples <= 4096:
        raise SoftgripError(f"--robust {args.robust}: expected the number of draws per candidate, 1 to 4096 "
                            f"(e.g. 16), 'linear', or 0 for none")
    pose = (args.pose_sigma or ROBUST_DEFAULTS["pose"]).split(",")
    if len(pose) != 2:
        raise SoftgripError(f"--pose-sigma {args.pose_sigma}: expected MM,RAD (e.g. {ROBUST_DEFAULTS['pose']})")
    # Every valid candidate is drawn (reach inf): the document and heat map give each one's P(closure).
    return {**({"linear": True} if linear else {"samples": samples, "reach": math.inf}), "pose_mm": _number(pose[0], "--pose-sigma (mm)", 0.0, 100.0),
            "pose_rad": _number(pose[1], "--pose-sigma (rad)", 0.0, 1.0),
            "mu_spread": _number(ROBUST_DEFAULTS["mu_spread"] if args.mu_spread is None else args.mu_spread,
                                 "--mu-spread", 0.0, 1.0, high_open=True),
            "contour_mm": _number(ROBUST_DEFAULTS["contour"] if args.contour_sigma is None else args.contour_sigma,
                                  "--contour-sigma", 0.0, 100.0)}


def parse_mu(text: str | None) -> float:
    """``--mu``: the friction coefficient, a finite number in :data:`MU_RANGE` (None: the default
    :data:`~softgrip_jax._quality.DEFAULT_MU`); a SoftgripError naming --mu otherwise."""
    if text is None:
        return DEFAULT_MU
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    low, high = MU_RANGE
    if not (math.isfinite(value) and low <= value <= high):
        raise SoftgripError(f"--mu {text}: expected the friction coefficient, a number from {low:g} to {high:g} "
                            f"(default {DEFAULT_MU})")
    return value


def check_distinct_outputs(outputs: dict[str, str]) -> None:
    """Refuse two output options (``{flag: path}``) that name the same file."""
    seen: dict[str, str] = {}
    for flag, path in outputs.items():
        real = os.path.realpath(path)
        if real in seen:
            raise SoftgripError(f"{seen[real]} and {flag} name the same file {path}: give two file names")
        seen[real] = flag


def write_json_stream(write, header: dict, scene: pipe.FrameScene, poses: np.ndarray, result,
                      shown: np.ndarray, robust: bool = False) -> None:
    """Write ``header`` with its ``"candidates"`` list (``shown``, in order) through ``write`` (a
    function taking text) as one JSON object and a newline, a few hundred candidates at a time:
    memory stays that of a few hundred candidates however many there are."""
    text = json.dumps(header, allow_nan=False)
    write(text[:-1] + ', "candidates": [')
    chunk: list[str] = []
    for k, i in enumerate(shown):
        chunk.append(json.dumps(pipe.candidate_json(poses[i], pipe.take(result, int(i)), scene.gripper, scene.camera,
                                                    robust=robust), allow_nan=False))
        if len(chunk) == 256 or k == len(shown) - 1:
            write((", " if k >= len(chunk) else "") + ", ".join(chunk))
            chunk = []
    write("]}\n")


# ---------------------------------------------------------------------------------------------
# Poses


def parse_grid(spec: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``X0:X1:NX,Y0:Y1:NY,A0:A1:NA`` -> the values along x (mm), y (mm) and the angle (rad)."""
    parts = spec.split(",")
    if len(parts) != 3:
        raise PoseInputError(f"--grid {spec!r}: expected three ranges, {_GRID_FORMAT}")
    axes = []
    for part, what in zip(parts, ("x", "y", "angle")):
        fields = part.split(":")
        try:
            if len(fields) != 3:
                raise ValueError
            lo, hi, count = float(fields[0]), float(fields[1]), int(fields[2])
        except ValueError:
            raise PoseInputError(f"--grid {spec!r}: the {what} range {part!r} is not FROM:TO:COUNT; expected "
                                 f"{_GRID_FORMAT}") from None
        if not (math.isfinite(lo) and math.isfinite(hi)) or not 1 <= count <= MAX_POSES:
            raise PoseInputError(f"--grid {spec!r}: the {what} range {part!r} needs finite ends and a count from 1 "
                                 f"to {MAX_POSES}")
        with np.errstate(over="ignore", invalid="ignore"):
            values = np.linspace(lo, hi, count)
        if not np.isfinite(values).all():
            raise PoseInputError(f"--grid {spec!r}: the {what} range {part!r} is too wide to step through (its "
                                 f"values overflow); give ends within +-1e300")
        axes.append(values)
    total = math.prod(len(a) for a in axes)
    if total > MAX_POSES:
        raise PoseInputError(f"--grid {spec!r} has {total} poses; at most {MAX_POSES} per call (split the grid)")
    return axes[0], axes[1], axes[2]


def grid_poses(xs: np.ndarray, ys: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(NX * NY * NA, 3) poses, x slowest, angle fastest."""
    return np.stack(np.meshgrid(xs, ys, angles, indexing="ij"), axis=-1).reshape(-1, 3)


def default_grid(scene: pipe.FrameScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The default grid (see EPILOG); around the frame's own pose when there is no object."""
    nx, ny, _ = DEFAULT_GRID_SHAPE
    angles = scene.pose[2] + np.asarray(DEFAULT_ANGLES)
    if not scene.has_object:
        x, y = scene.pose[:2]
        return np.linspace(x - 20.0, x + 20.0, nx), np.linspace(y - 20.0, y + 20.0, ny), angles
    rows, cols = np.nonzero(scene.segmentation.object)
    (x0, y0), (x1, _) = scene.camera.px_to_mm([[cols.min() - 0.5, rows.min() - 0.5],
                                               [cols.max() + 0.5, rows.max() + 0.5]])
    reach = max(float(scene.gripper.left.length), float(scene.gripper.right.length))
    return (np.linspace(x0 - DEFAULT_MARGIN_MM, x1 + DEFAULT_MARGIN_MM, nx), np.linspace(y0 - reach, y0, ny),
            angles)


def read_poses(path: str) -> np.ndarray:
    """(B, 3) poses from a .json or .csv file (formats in EPILOG), or standard input for ``"-"``,
    read through the input guard (``softgrip_base.input_guard``: a regular file, at most
    ``input_guard.MAX_POSE_BYTES``).

    Raises:
        PoseInputError: a missing or unreadable file, or a bad entry (named by its line).
    """
    if path == "-":
        return _stdin_poses()
    file = Path(path)
    suffix = file.suffix.lower()
    if suffix not in (".json", ".csv"):
        raise PoseInputError(f"{file}: a pose file must be .json or .csv, got {suffix or 'no suffix'!r}")
    text = input_guard.read_user_text(file, what="the pose file", max_bytes=input_guard.MAX_POSE_BYTES,
                                      error=PoseInputError, missing="no such pose file")
    poses = _json_poses(text, file) if suffix == ".json" else _csv_poses(text, file)
    if len(poses) == 0:
        raise PoseInputError(f"{file}: no poses in the file")
    if len(poses) > MAX_POSES:
        raise PoseInputError(f"{file}: {len(poses)} poses; at most {MAX_POSES} per call (split the file)")
    return np.asarray(poses, np.float64)


def _stdin_poses() -> np.ndarray:
    """Poses from standard input (at most ``input_guard.MAX_POSE_BYTES``): JSON when it starts with
    '[' or '{', else CSV."""
    label = Path("<stdin>")
    stream = getattr(sys.stdin, "buffer", None)
    if stream is not None:
        data = input_guard.read_user_stream(stream, what="--poses - (standard input)",
                                            max_bytes=input_guard.MAX_POSE_BYTES, error=PoseInputError)
        text = input_guard.decode_user_text(data, "-", what="--poses", error=PoseInputError)
    else:  # a text stream without bytes beneath (replaced in-process)
        try:
            text = sys.stdin.read(input_guard.MAX_POSE_BYTES + 1)
        except (OSError, UnicodeDecodeError) as err:
            raise PoseInputError(f"--poses -: cannot read standard input ({err})") from None
        if len(text) > input_guard.MAX_POSE_BYTES:
            raise PoseInputError(f"--poses -: standard input holds more than {input_guard.MAX_POSE_BYTES} "
                                 f"characters, more than softgrip reads there (split it)")
        text = text.removeprefix("\ufeff")
    poses = _json_poses(text, label) if text.lstrip()[:1] in ("[", "{") else _csv_poses(text, label)
    if len(poses) == 0:
        raise PoseInputError(f"{label}: no poses on standard input")
    if len(poses) > MAX_POSES:
        raise PoseInputError(f"{label}: {len(poses)} poses; at most {MAX_POSES} per call (split the input)")
    return np.asarray(poses, np.float64)


def _json_poses(text: str, file: Path) -> list[tuple[float, float, float]] | np.ndarray:
    try:
        data = user_json.loads(text)
    except json.JSONDecodeError as err:
        raise PoseInputError(f"{file}, line {err.lineno}: not valid JSON ({err.msg}, column {err.colno})") from None
    key = None
    if isinstance(data, dict):
        key = next((k for k in ("poses", "candidates") if isinstance(data.get(k), list)), None)
        if key is None:
            # The keys are not quoted: a JSON file of other data (a token, a key store) stays unprinted.
            raise PoseInputError(f'{file}, line 1: expected a list of poses, or an object with a "poses" list, '
                                 f'got an object with {len(data)} other key(s): is it the right file?')
        items = data[key]
    elif isinstance(data, list):
        items = data
    else:
        raise PoseInputError(f"{file}, line 1: expected a list of poses, got {type(data).__name__}")
    fast = _numeric_rows(items)
    if fast is not None:
        return fast
    poses = []
    for i, item in enumerate(items):
        try:
            poses.append(_json_pose(item, f"{file}, pose {i + 1}"))
        except PoseInputError as err:
            if not _mostly_json_poses(items):  # other data: say where, never what
                err = PoseInputError(f"{file}, pose {i + 1}: not a pose file (most entries are not poses: "
                                     f"expected [x_mm, y_mm(, angle_rad)] or {{\"x_mm\", \"y_mm\", "
                                     f"\"angle_rad\"}}): is it the right file?")
            # Name the line: found only now, as scanning for every element's line is slow.
            lines = _element_lines(text, key, len(items))
            if lines is None:
                raise err from None
            raise PoseInputError(str(err).replace(f"{file}, pose {i + 1}", f"{file}, line {lines[i]}", 1)) from None
    return poses


def _mostly_json_poses(items: list) -> bool:
    """Whether at least half of ``items`` (and at least one) are poses: only then is a bad entry
    quoted in a message (a JSON file of other data is never echoed)."""
    good = 0
    for item in items:
        try:
            _json_pose(item, "")
        except PoseInputError:
            continue
        good += 1
    return good >= 1 and 2 * good >= len(items)


def _numeric_rows(items: list) -> np.ndarray | None:
    """(B, 3) poses when every item is a list of 2 or 3 finite numbers (the common, large case: read
    at numpy's speed), else None (the item-by-item reader then names the bad item)."""
    number = (int, float)
    try:
        if not all(type(row) is list and 2 <= len(row) <= 3 for row in items):
            return None
        if not all(type(v) in number for row in items for v in row):
            return None
        if all(len(row) == 3 for row in items):
            poses = np.array(items, np.float64)
        else:
            poses = np.zeros((len(items), 3))
            for i, row in enumerate(items):
                poses[i, :len(row)] = row
    except (OverflowError, ValueError):
        return None
    return poses if np.isfinite(poses).all() else None


def _json_pose(item, where: str) -> tuple[float, float, float]:
    expected = 'expected [x_mm, y_mm] or [x_mm, y_mm, angle_rad], or {"x_mm", "y_mm", "angle_rad"}'
    if isinstance(item, dict) and isinstance(item.get("pose"), dict):
        item = item["pose"]  # a candidate of `softgrip score --json`
    if isinstance(item, dict):
        unknown = sorted(set(item) - {"x_mm", "y_mm", "angle_rad"})
        if unknown or "x_mm" not in item or "y_mm" not in item:
            raise PoseInputError(f"{where}: {expected}, got {_show(item)}")
        values = [item["x_mm"], item["y_mm"], item.get("angle_rad", 0.0)]
    elif isinstance(item, list) and len(item) in (2, 3):
        values = list(item) + [0.0] * (3 - len(item))
    else:
        raise PoseInputError(f"{where}: {expected}, got {_show(item)}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        raise PoseInputError(f"{where}: pose values must be finite numbers, got {_show(item)}")
    return float(values[0]), float(values[1]), float(values[2])


def _element_lines(text: str, key: str | None, count: int) -> list[int] | None:
    """Line numbers of the elements of the pose list (top-level, or under ``key``); None if unsure."""
    if key is None:
        start = len(text) - len(text.lstrip())
    else:
        match = re.search(r'"%s"\s*:\s*\[' % re.escape(key), text)
        if match is None:
            return None
        start = match.end() - 1
    decoder, gap, lines = json.JSONDecoder(), re.compile(r"[\s,]*"), []
    i = start + 1
    try:
        while True:
            found = gap.match(text, i)  # (it always matches: the pattern matches the empty string too)
            if found is None:
                return None
            i = found.end()
            if i >= len(text) or text[i] == "]":
                break
            lines.append(text.count("\n", 0, i) + 1)
            _, i = decoder.raw_decode(text, i)
    except (ValueError, RecursionError):  # what user_json.loads reads but raw_decode cannot: no lines
        return None
    return lines if len(lines) == count else None


_COLUMN_NAMES = {"x_mm": 0, "x": 0, "y_mm": 1, "y": 1, "angle_rad": 2, "angle": 2}


#: The separators a pose CSV may use: ',' (softgrip's own), ';' (spreadsheets in locales with a decimal
#: comma) and tab.
CSV_DELIMITERS = (",", ";", "\t")
_DECIMAL_COMMA = re.compile(r"[+-]?\d+,\d+")
_SAMPLE_ROWS = 50


def _csv_poses(text: str, file: Path) -> list[tuple[float, float, float]]:
    """Poses from CSV ``text`` (file name ``file`` for messages): rows of x_mm,y_mm[,angle_rad]
    separated by :func:`_csv_delimiter`, an optional header. A bad row is quoted in the message only
    when most rows are pose rows (:func:`_mostly_pose_rows`): a file of other data is named by line
    and column, never echoed."""
    delimiter = _csv_delimiter(text)
    sep = "<tab>" if delimiter == "\t" else delimiter

    def bad(line_no: int, problem: str, cells: list[str], column: int | None = None) -> PoseInputError:
        """The error for a bad row; ``problem`` has a ``{}`` where the row is quoted. A number with a
        decimal comma is named as the cause first (checked only here: rows that read are not slowed)."""
        comma = next((k for k, c in enumerate(cells) if _DECIMAL_COMMA.fullmatch(c)), None)
        if comma is not None:
            return PoseInputError(f"{file}, line {line_no}, column {comma + 1}: a decimal comma; softgrip reads "
                                  f"numbers with a decimal point (0.5, not 0,5): save the file with '.' as the "
                                  f"decimal separator")
        if _mostly_pose_rows(text, delimiter):
            return PoseInputError(f"{file}, line {line_no}: " + problem.format(repr(delimiter.join(cells))))
        where = f"line {line_no}" + (f", column {column}" if column else "")
        return PoseInputError(f"{file}, {where}: not a pose file (most rows are not x_mm{sep}y_mm[{sep}angle_rad] "
                              f"numbers): is it the right file?")

    poses: list[tuple[float, float, float]] = []
    columns = None
    for line_no, row in _csv_rows(text, file, delimiter):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if columns is None and not poses and not _numeric(cells[0]):
            names = [c.lower() for c in cells]
            bad_names = [n for n in names if n not in _COLUMN_NAMES]
            if bad_names or len({_COLUMN_NAMES[n] for n in names}) != len(names) \
                    or not {0, 1} <= {_COLUMN_NAMES[n] for n in names}:
                raise bad(line_no, "a header must name the columns x_mm, y_mm and optionally angle_rad, got {}",
                          cells, 1 + names.index(bad_names[0]) if bad_names else None)
            columns = [_COLUMN_NAMES[n] for n in names]
            continue
        expected = len(columns) if columns else None
        if (expected and len(cells) != expected) or (not expected and len(cells) not in (2, 3)):
            want = f"{expected} values" if expected else "2 or 3 values (x_mm, y_mm[, angle_rad])"
            raise bad(line_no, f"expected {want}, got {len(cells)}: {{}}", cells)
        try:
            values = [float(c) for c in cells]
        except ValueError:
            column = next(k for k, c in enumerate(cells) if not _numeric(c)) + 1
            raise bad(line_no, "not a number in {}", cells, column) from None
        if not all(math.isfinite(v) for v in values):
            raise bad(line_no, "pose values must be finite, got {}", cells)
        pose = [0.0, 0.0, 0.0]
        for index, value in zip(columns or range(len(values)), values):
            pose[index] = value
        poses.append((pose[0], pose[1], pose[2]))
    return poses


def _csv_delimiter(text: str) -> str:
    """The separator of CSV ``text`` among :data:`CSV_DELIMITERS`: the one that splits the first
    rows (comments and blank lines left out) into 2 or 3 cells each; ',' when none or several do.
    A ';' file whose numbers use a decimal comma is then refused by :func:`_csv_poses`, never read
    as more columns."""
    lines = []
    for line in io.StringIO(text):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            lines.append(stripped)
            if len(lines) == _SAMPLE_ROWS:
                break
    if not lines:
        return ","
    fits = [d for d in CSV_DELIMITERS if all(2 <= len(line.split(d)) <= 3 for line in lines[1:] or lines)]
    if "," in fits and len(fits) > 1 and any(";" in line or "\t" in line for line in lines):
        fits.remove(",")  # "0,5;1,2" splits into 2 both ways: the decimal comma is the trap
    return fits[0] if len(fits) == 1 else ","


def _mostly_pose_rows(text: str, delimiter: str) -> bool:
    """Whether at least half of the rows of ``text`` (a header, comments and blank lines left out;
    at least one) are 2 or 3 numbers: a file that looks like a pose file."""
    try:
        rows = [[c.strip() for c in row] for row in csv.reader(io.StringIO(text), delimiter=delimiter)]
    except csv.Error:
        return False
    rows = [row for row in rows if any(row) and not row[0].startswith("#")]
    if rows and not _numeric(rows[0][0]):
        rows = rows[1:]  # a header
    good = sum(2 <= len(row) <= 3 and all(_numeric(c) for c in row) for row in rows)
    return good >= 1 and 2 * good >= len(rows)


def _csv_rows(text: str, file: Path, delimiter: str = ","):
    """(line number, cells) of each row; a row the csv module cannot split is a PoseInputError."""
    reader = csv.reader(io.StringIO(text), delimiter=delimiter)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as err:
            raise PoseInputError(f"{file}, line {reader.line_num}: not a CSV row ({err}); expected "
                                 f"x_mm,y_mm[,angle_rad]") from None
        yield reader.line_num, row


def _numeric(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _show(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def score_poses(scene: pipe.FrameScene, poses: np.ndarray, estimator=None, mu: float = DEFAULT_MU, uncertainty=None):
    """Score (B, 3) poses on ``scene`` in one compiled call (``softgrip_vision.scene.Scene.score``), with the
    deformation ``estimator`` (``softgrip_jax.Geometric()`` or ``Mechanics(config)``; None: the default)
    and the friction coefficient ``mu`` (``softgrip_jax.ScoreWeights(mu=...)``; a run-time value: no
    recompilation when it changes), robust with ``uncertainty`` (a ``softgrip_jax.Uncertainty``).

    Returns:
        The ``Score`` with numpy leaves of leading axis B, and the seconds it took (compilation
        included the first time an estimator is used).
    """
    from tqdm import tqdm

    from softgrip_jax import ScoreWeights

    name = getattr(estimator, "name", None) or "mechanics"
    # The first call of an estimator compiles for up to a minute or two: said before it starts, and a
    # bar over the poses on a terminal (tqdm's disable=None: off when stderr is not a terminal).
    pipe.note(f"scoring {len(poses)} candidate poses ({name} estimate; the first run of an estimator "
              f"compiles it, later runs load it from the compilation cache)")
    start = time.perf_counter()
    with tqdm(total=len(poses), desc="score", unit="pose", file=sys.stderr, leave=False,
              disable=True if pipe.quiet() else None) as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        result = scene.score(poses, estimator=estimator, weights=ScoreWeights(mu=mu), uncertainty=uncertainty,
                             progress=progress)
    return result, time.perf_counter() - start


#: Candidate indices, best score first; invalid candidates last, each group in input order.
rank = scene_api.rank


# ---------------------------------------------------------------------------------------------
# Output


def _table(scene: pipe.FrameScene, poses: np.ndarray, result, shown: np.ndarray, n_valid: int,
           robust: bool = False) -> str:
    """The ranked candidates as text: pose, score, grasp quality (0 without force closure; with
    ``robust``, P(closure) too), both fingers' contact cases and the status."""
    from softgrip_jax import CASE_NAMES

    extra = f" {'P(closure)':>10}" if robust else ""
    lines = [f"{one_line(scene.path)}: {len(poses)} candidate poses, {n_valid} valid; "
             f"{int(np.sum(result.force_closure))} in force closure; best first",
             f"{'rank':>4}  {'x (mm)':>8} {'y (mm)':>8} {'angle':>7}  {'score':>7} {'quality':>7}{extra}  "
             f"{'left':<14} {'right':<14} status"]
    for k, i in enumerate(shown, start=1):
        x, y, a = poses[i]
        valid = bool(result.valid[i])
        value = f"{float(result.score[i]):7.3f}" if valid else f"{'-':>7}"
        quality = f"{float(result.quality[i]):7.3f}" if valid else f"{'-':>7}"
        if robust:
            quality += f" {float(result.p_closure[i]):10.3f}" if valid else f" {'-':>10}"
        cases = [CASE_NAMES[int(getattr(result.grasp, side).case[i])] for side in pipe.SIDES]
        status = pipe.status_name(result.status[i], bool(result.penetrating[i]))
        lines.append(f"{k:>4}  {x:8.2f} {y:8.2f} {a:7.3f}  {value} {quality}  {cases[0]:<14} {cases[1]:<14} {status}")
    return "\n".join(lines)


#: RGB of a position with valid candidates but none in force closure, and of one with none valid.
_NO_CLOSURE_RGB = (220, 220, 220)
_NO_VALID_RGB = (128, 128, 128)


def heatmap_image(scene: pipe.FrameScene, poses: np.ndarray, result, grid, best: int,
                  mu: float = DEFAULT_MU) -> np.ndarray:
    """The heat map drawn with OpenCV on the frame's pixels (the demo's picture when matplotlib is
    not installed; ``softgrip_vision.plots.heatmap_figure`` is the plot with mm axes): the frame with the
    best grasp quality over the angles at each gripper-centre position (viridis from 0 to the
    highest; light grey where valid candidates have no force closure, grey where no angle is valid),
    the best candidate's estimate (joints blue, contacts red) and its centre and base line, a colour
    bar and a caption. ``mu``: the friction the scores were computed with (for the caption)."""
    from softgrip_vision.plots import closure_quality, quality_cells, quality_label

    rgb = scene.frame.color
    h, w = rgb.shape[:2]
    quality, valid_all = closure_quality(result)
    finite = quality[np.isfinite(quality)]
    lo, hi = 0.0, (float(finite.max()) if finite.size and finite.max() > 0 else 1.0)

    def colours(values: np.ndarray) -> np.ndarray:
        level = np.clip((values - lo) / (hi - lo) if hi > lo else np.ones_like(values), 0.0, 1.0)
        level = np.nan_to_num(level, nan=0.0)
        mapped = cv2.applyColorMap(np.rint(255 * level).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS)
        return mapped.reshape(values.shape + (3,))[..., ::-1]

    layer = np.zeros_like(rgb)
    alpha = np.zeros((h, w), np.float32)
    if grid is not None:
        xs, ys, angles = grid
        cells, any_valid = quality_cells(result, grid)  # rows: y, columns: x
        step_x = (xs[-1] - xs[0]) / (len(xs) - 1) if len(xs) > 1 else 2.0
        step_y = (ys[-1] - ys[0]) / (len(ys) - 1) if len(ys) > 1 else 2.0
        (u0, v0), (u1, v1) = scene.camera.mm_to_px([[xs[0] - step_x / 2, ys[0] - step_y / 2],
                                                    [xs[-1] + step_x / 2, ys[-1] + step_y / 2]])
        col = np.floor((np.arange(w) - u0) / (u1 - u0) * len(xs)).astype(int)
        row = np.floor((np.arange(h) - v0) / (v1 - v0) * len(ys)).astype(int)
        us, vs = np.flatnonzero((col >= 0) & (col < len(xs))), np.flatnonzero((row >= 0) & (row < len(ys)))
        if us.size and vs.size:
            block = cells[np.ix_(row[vs], col[us])]
            coloured = colours(block)
            coloured[~np.isfinite(block)] = _NO_CLOSURE_RGB
            coloured[~any_valid[np.ix_(row[vs], col[us])]] = _NO_VALID_RGB
            layer[np.ix_(vs, us)] = coloured
            alpha[np.ix_(vs, us)] = np.where(np.isfinite(block), 0.65, 0.35)
    else:
        scores = np.where(valid_all, np.asarray(result.score, np.float64), -np.inf)
        order = np.argsort(scores, kind="stable")  # best drawn last, on top
        centres = scene.camera.mm_to_px(poses[order, :2])
        for (u, v), value, ok in zip(centres, quality[order], valid_all[order]):
            if not (np.isfinite(u) and np.isfinite(v)) or not (-10 <= u < w + 10 and -10 <= v < h + 10):
                continue
            colour = (_NO_VALID_RGB if not ok else _NO_CLOSURE_RGB if not np.isfinite(value)
                      else tuple(int(c) for c in colours(np.array([value]))[0]))
            centre = (int(round(u)), int(round(v)))
            cv2.circle(layer, centre, 5, colour, -1)
            cv2.circle(alpha, centre, 5, 0.8 if ok else 0.4, -1)
    blended = (rgb * (1.0 - alpha[..., None]) + layer * alpha[..., None]).round().astype(np.uint8)

    chosen = pipe.take(result, best)
    valid = bool(chosen.valid)
    image = pipe.grasp_overlay(blended, chosen.grasp, scene.camera) if valid else blended
    if valid:
        x, y, angle = poses[best]
        bases = [np.asarray(frame.origin, np.float64) for frame in finger_frames(scene.gripper, poses[best])]
        ends = scene.camera.mm_to_px(np.array(bases))
        best_centre = scene.camera.mm_to_px([x, y])
        for colour, width in (((255, 255, 255), 4), ((0, 0, 0), 1)):
            cv2.line(image, tuple(np.rint(ends[0]).astype(int)), tuple(np.rint(ends[1]).astype(int)), colour, width,
                     cv2.LINE_AA)
        cv2.drawMarker(image, tuple(np.rint(best_centre).astype(int)), (255, 255, 255), cv2.MARKER_CROSS, 14, 3)
        cv2.drawMarker(image, tuple(np.rint(best_centre).astype(int)), (0, 0, 0), cv2.MARKER_CROSS, 12, 1)
    _colour_bar(image, lo, hi, colours, finite.size > 0)
    if valid:
        x, y, angle = poses[best]
        best_text = (f"best: x {x:.1f} mm, y {y:.1f} mm, angle {angle:.2f} rad, score {float(chosen.score):.2f}, "
                     f"quality {float(chosen.quality):.3f}")
    else:
        best_text = "no valid candidate"
    pipe.caption(image, "\n".join([
        f"{scene.name}: {quality_label(mu)}, best over {len(grid[2]) if grid else 'the'} angles at each position",
        "light grey: no force closure; grey: no valid grasp; cross: best pose's centre, bar: its finger bases",
        "blue: best pose's estimated fingers, red: contacts", best_text]), (8, image.shape[0] - 8), bottom=True)
    return image


def _colour_bar(image: np.ndarray, lo: float, hi: float, colours, any_valid: bool) -> None:
    """A vertical viridis bar at the right edge, labelled with the highest and lowest quality."""
    h, w = image.shape[:2]
    height, width = min(160, h // 2), 14
    x0, y0 = w - width - 56, 30
    if x0 < 0:
        return
    pipe.caption(image, "quality", (x0 - 6, 6), scale=0.4)
    values = lo + (hi - lo) * np.linspace(1.0, 0.0, height)[:, None] * np.ones((1, width))
    image[y0:y0 + height, x0:x0 + width] = colours(values) if any_valid else 128
    cv2.rectangle(image, (x0 - 1, y0 - 1), (x0 + width, y0 + height), (255, 255, 255), 1)
    if any_valid:
        pipe.caption(image, f"{hi:.2f}", (x0 + width + 3, y0 - 2), scale=0.4)
        pipe.caption(image, f"{lo:.2f}", (x0 + width + 3, y0 + height - 16), scale=0.4)
