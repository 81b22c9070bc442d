"""``softgrip calibrate``: a calibration profile from one frame pair (eq. 4) or by least squares."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from softgrip_jax import SoftgripError
from softgrip_cli._args import add_method_argument, positive_int, resolve_method

DEFAULT_N_LINKS = 10

EPILOG = """\
examples:
  softgrip calibrate closed_0 --open open_0 --n-links 10 -o profile.json
      one-frame calibration (eqs. 4-5): Theta of each finger from a frame of the gripper closed
      without an object, L, r and the base separation from a frame of the open gripper
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 open_3 closed_3 -o fitted.json
      least squares over open/closed frame pairs (objects allowed), starting from the first open
      frame and Theta = 0.5 rad
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 --profile profile.json --base-offset \\
      --json -o fitted.json
      start from a profile (its N, L, r, segmentation), also fit a base offset per finger, and print
      the report as JSON
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 open_3 closed_3 --method mechanics \
      --stiffness --base-compliance -o fitted.json
      fit through the mechanics estimate (the spring-joint chain at equilibrium): Theta, the
      base-to-tip stiffness ratio and the base compliance of each finger; the pairs need objects
      that the closed fingers wrap, at different places along the fingers

Frame arguments are frame folders (color.png, depth.png, intrinsics.json; see `softgrip capture`).
In a fit, a pair that cannot be used (segmentation fails, the open finger already overlaps the
object, ...) is skipped with a warning and listed in the profile's fit.skipped. The first fit in a
process compiles for tens of seconds (longer with --method mechanics); progress goes to stderr.
The profile records the estimate a fit went through (fit.estimate_method); `softgrip estimate`,
`score` and `demo` use it unless given --method.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``calibrate`` on the ``softgrip`` sub-command parsers."""
    parser = subparsers.add_parser(
        "calibrate",
        help="make a calibration profile from frames (one pair, or least squares over several)",
        description="Calibrate the deformation model: Theta of each finger from a frame of the closed "
                    "gripper without an object and L from a frame of the open gripper (the paper's eqs. "
                    "4-5), or fit Theta (and optionally a base offset; through the mechanics estimate "
                    "also the stiffness ratio and base compliance) to several open/closed frame pairs by "
                    "robust least squares through the estimator.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("closed", nargs="?", type=Path, metavar="CLOSED_FRAME",
                        help="frame of the gripper closed without an object (one-frame calibration)")
    parser.add_argument("--open", type=Path, metavar="OPEN_FRAME", dest="open_frame",
                        help="frame of the open gripper (one-frame calibration)")
    parser.add_argument("--fit", nargs="+", type=Path, metavar="FRAME",
                        help="least squares over pairs OPEN CLOSED [OPEN CLOSED ...]")
    parser.add_argument("--profile", type=Path, metavar="START",
                        help="starting values for --fit (default: the first open frame, Theta 0.5 rad)")
    parser.add_argument("--n-links", type=_n_links, metavar="N",
                        help=f"number of links of the model (default: the --profile's, else {DEFAULT_N_LINKS})")
    parser.add_argument("--base-offset", action="store_true",
                        help="with --fit, also fit a base offset per finger (needs 2 or more pairs)")
    add_method_argument(parser, profile_text="the --profile")
    parser.add_argument("--stiffness", action="store_true",
                        help="with --fit --method mechanics, also fit each finger's base-to-tip stiffness ratio "
                             "(needs 2 or more pairs whose fingers touch an object)")
    parser.add_argument("--base-compliance", action="store_true",
                        help="with --fit --method mechanics, also fit each finger's base compliance (needs 2 or "
                             "more pairs whose fingers touch an object)")
    parser.add_argument("--base-end", choices=("auto", "rounded", "flat"), default=None,
                        help="the fingers' base ends: 'flat' where they are cut where they leave the gripper's "
                             "body (the base is the middle of the cut), 'rounded' for a capped end (the base "
                             "is the cap's centre), 'auto' to detect it (default: the --profile's, else auto)")
    parser.add_argument("--finger-relief", type=_relief, default=None, metavar="MM",
                        help="how far each finger's outline lies behind its nearest front-surface depth reading "
                             "(about r for a round finger, 0 for a flat front), or 'auto' to measure it from "
                             "the depth across the fingers (default: the --profile's, else auto)")
    parser.add_argument("--loss", choices=("huber", "cauchy"), default="huber",
                        help="robust loss of the fit (default: huber)")
    parser.add_argument("--loss-scale", type=float, default=1.0, metavar="MM",
                        help="scale of the robust loss in mm (default: 1.0)")
    parser.add_argument("--camera", metavar="NAME",
                        help="camera name or serial number to record (default: the --profile's, else "
                             "'unspecified')")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="PROFILE",
                        help="profile file to write (JSON; replaced atomically if it exists)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    parser.set_defaults(func=run)
    return parser


def _n_links(text: str) -> int:
    """An argparse type: a number of links from 1 to the profile format's MAX_N_LINKS."""
    from calib.profile import MAX_N_LINKS

    value = positive_int(text)
    if value > MAX_N_LINKS:
        raise argparse.ArgumentTypeError(f"at most {MAX_N_LINKS} links, got {value}")
    return value


def _relief(text: str):
    """An argparse type: ``auto`` or a relief in mm (validated by MeasureSettings)."""
    if text == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a number of mm, got {text!r}") from None


def _measure_settings(args: argparse.Namespace, start=None):
    """The measurement settings: the --profile's (if any) with --base-end / --finger-relief applied."""
    from vision.measure import MeasureSettings

    base = start.measure_settings() if start is not None else MeasureSettings()
    relief = base.finger_relief_mm if args.finger_relief is None else (
        None if args.finger_relief == "auto" else args.finger_relief)
    return MeasureSettings(base_end=args.base_end or base.base_end, finger_relief_mm=relief)


def run(args: argparse.Namespace) -> int:
    """Calibrate as ``args`` says, write the profile, print a report; 0 on success."""
    from calib.fit import SkippedFrameWarning
    from softgrip_cli._pipeline import check_output_file

    check_output_file(args.output, "-o")  # before a fit that may take minutes
    with warnings.catch_warnings():
        warnings.simplefilter("always", SkippedFrameWarning)
        warnings.showwarning = _print_warning
        profile = _fit(args) if args.fit else _one_frame(args)
    from calib.profile import save_profile

    save_profile(profile, args.output)
    if args.json:
        print(json.dumps({"output": str(args.output), "profile": profile.to_dict()}))
    else:
        _print_summary(profile, args.output)
    return 0


def _one_frame(args: argparse.Namespace):
    from calib.one_frame import one_frame_from_frames
    from vision.frames import load_frame

    if args.closed is None or args.open_frame is None:
        raise SoftgripError("give CLOSED_FRAME and --open OPEN_FRAME for a one-frame calibration, or --fit OPEN "
                            "CLOSED [...] for least squares (see softgrip calibrate --help)")
    fit_only = [f"--{name.replace('_', '-')}" for name in ("profile", "base_offset", "method", "stiffness",
                                                           "base_compliance")
                if getattr(args, name) not in (None, False)]
    if fit_only:
        raise SoftgripError(f"{', '.join(fit_only)} only apply to --fit")
    return one_frame_from_frames(load_frame(args.closed), load_frame(args.open_frame),
                                 args.n_links or DEFAULT_N_LINKS, label=f"{args.open_frame} + {args.closed}",
                                 camera_name=args.camera or "unspecified",
                                 names=(str(args.closed), str(args.open_frame)), measure=_measure_settings(args))


def _fit(args: argparse.Namespace):
    import dataclasses

    from calib.fit import fit, load_observations, start_from_open_frame
    from calib.profile import load_profile
    from vision.frames import load_frame

    if args.closed is not None or args.open_frame is not None:
        raise SoftgripError("CLOSED_FRAME and --open are for a one-frame calibration; with --fit give the frames "
                            "as pairs: --fit OPEN CLOSED [OPEN CLOSED ...]")
    if len(args.fit) % 2:
        raise SoftgripError(f"--fit needs frame pairs OPEN CLOSED, got {len(args.fit)} folders (an odd number)")
    pairs = list(zip(args.fit[0::2], args.fit[1::2]))
    if args.profile is not None:
        start = load_profile(args.profile)
        n_links = start.fingers["left"].n_links
        if args.n_links is not None and args.n_links != n_links:
            raise SoftgripError(f"--n-links {args.n_links} differs from n_links = {n_links} in {args.profile}; "
                                f"drop --n-links, or calibrate a new profile with that N")
        if args.camera is not None:
            start = dataclasses.replace(start, camera={**start.camera, "name": args.camera})
        settings = start.segmentation_settings()
    else:
        n_links = args.n_links or DEFAULT_N_LINKS
        try:
            start = start_from_open_frame(load_frame(pairs[0][0]), n_links, camera_name=args.camera or "unspecified",
                                          measure=_measure_settings(args))
        except SoftgripError as err:  # the starting values come from the first open frame: name it
            message = str(err)
            raise type(err)(message if str(pairs[0][0]) in message else f"{pairs[0][0]}: {message}") from None
        settings = None
    method = resolve_method(args.method, start if args.profile is not None else None)
    mechanics_only = [flag for flag, on in (("--stiffness", args.stiffness),
                                            ("--base-compliance", args.base_compliance)) if on]
    if mechanics_only and method != "mechanics":
        raise SoftgripError(f"{' and '.join(mechanics_only)} only change the mechanics estimate; add --method "
                            f"mechanics (the fit is going through the {method} estimate)")
    parameters = ["theta_entire"] + [name for name, on in (("base_offset", args.base_offset),
                                                            ("stiffness_ratio", args.stiffness),
                                                            ("base_compliance", args.base_compliance)) if on]
    measure = _measure_settings(args, start)
    observations, skipped = load_observations(pairs, settings, n_links, progress=True, measure=measure)
    fitted = fit(observations, start, parameters, loss=args.loss, loss_scale_mm=args.loss_scale, method=method,
                 skipped=skipped)
    return dataclasses.replace(fitted, vision={**fitted.vision, **measure.to_dict()})


def _print_summary(profile, output: Path) -> None:
    errors = profile.fit.standard_errors
    for side, f in profile.fingers.items():
        se = errors.get(f"{side}.theta_entire")
        spread = "" if se is None else f" +/- {se:.4f}"
        offset = ""
        if f"{side}.base_offset" in errors:
            offset = ", base offset ({:+.2f}, {:+.2f}) mm".format(*f.base_offset)
        mechanics = ""
        for name, label in (("stiffness_ratio", "stiffness ratio"), ("base_compliance", "base compliance")):
            if f"{side}.{name}" in errors:
                mechanics += f", {label} {getattr(f, name):.3f} +/- {errors[f'{side}.{name}']:.3f}"
        print(f"{side:<5} Theta {f.theta_entire:.4f}{spread} rad, L {f.length:.2f} mm, r {f.half_thickness:.2f} mm, "
              f"N {f.n_links}{offset}{mechanics}")
    fit = profile.fit
    skipped = f", {len(fit.skipped)} skipped" if fit.skipped else ""
    through = f" ({fit.estimate_method} estimate)" if fit.estimate_method else ""
    print(f"base separation {profile.base_separation:.2f} mm; {fit.method}: residual RMS {fit.residual_rms_mm:.3f} mm "
          f"over {len(fit.frames)} frame pair(s){through}{skipped}")
    print(f"wrote {output}")


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"softgrip calibrate: warning: {message}", file=sys.stderr)
