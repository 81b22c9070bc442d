"""``softgrip calibrate``: a calibration profile from one frame pair (eq. 4) or by least squares."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

from softgrip_base.input_guard import one_line
from softgrip_jax import SoftgripError
from softgrip_cli._args import add_method_argument, positive_int, resolve_estimator

DEFAULT_N_LINKS = 10

#: How much worse (mm of residual RMS) the fit may leave the free closure than it was at the start
#: before the command warns.
FREE_CLOSURE_TOLERANCE_MM = 0.1

EPILOG = """\
examples:
  softgrip calibrate closed_0 --open open_0 --n-links 10 -o profile.json
      one-frame calibration (eqs. 4-5): Theta of each finger from a frame of the gripper closed
      without an object, L, r and the base separation from a frame of the open gripper
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 open_3 closed_3 -o fitted.json
      least squares over open/closed frame pairs (objects allowed), starting from the first open
      frame and Theta = 0.5 rad
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 --empty open_0 closed_0 -o fitted.json
      the same with a calibration pair (open; closed without an object) in the fit's data, so that
      the fit keeps the free closure; it starts from that pair's one-frame calibration
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 --profile profile.json --base-offset \\
      --json -o fitted.json
      start from a profile (its N, L, r, segmentation), also fit a base offset per finger, and print
      the report as JSON
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 open_3 closed_3 --empty open_0 closed_0 \\
      -o fitted.json
      through the mechanics estimate (the default), the pairs also choose the stiffness model:
      a uniform finger clamped at its base, + a base-to-tip stiffness ratio, + a compliant base.
      Each model is fitted to all pairs and predicts each pair with an object from the others;
      a richer model is kept only when it predicts them clearly better (the report lists each
      model's errors and why one was chosen; the profile's fit.model_selection records them)
  softgrip calibrate --fit open_1 closed_1 open_2 closed_2 open_3 closed_3 --stiffness \\
      --base-compliance -o fitted.json
      fit the given stiffness parameters instead of choosing (--uniform: Theta only); the pairs
      need objects that the closed fingers wrap, at different places along the fingers

Frame arguments are frame folders (color.png, depth.png, intrinsics.json; see `softgrip capture`).
A fit over pairs with objects alone can bend Theta to make up for errors in the measured L, r or
bases and so make the gripper's closure without an object worse. The pair of the free closure is
therefore part of the fit when it is known: --empty OPEN CLOSED, else the pair a --profile records
(a one-frame calibration's frames, or a fit's fit.free_closure) if its folders exist (relative
paths: from here, else next to the profile). The report lists every pair's residual (RMS, and the
mean joint error at joint N/2 and at the tip, mm), the free closure's next to its residual at the
start, and warns when the fit made the free closure worse by more than 0.1 mm.
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
    parser.add_argument("--empty", nargs=2, type=Path, metavar=("OPEN", "CLOSED"),
                        help="with --fit, a calibration pair in the fit's data: a frame of the open gripper and "
                             "one of the gripper closed without an object (the free closure); default: the pair "
                             "the --profile records, if its folders exist")
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
    parser.add_argument("--uniform", action="store_true",
                        help="with --fit --method mechanics, keep the uniform finger clamped at its base (fit "
                             "Theta only) instead of letting the pairs choose the stiffness model")
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
                        help="profile file to write (JSON; replaced atomically if it exists; never one of the "
                             "command's inputs)")
    from softgrip_cli._pipeline import add_force_argument

    add_force_argument(parser)
    parser.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    parser.set_defaults(func=run)
    return parser


def _n_links(text: str) -> int:
    """An argparse type: a number of links from 1 to the profile format's MAX_N_LINKS."""
    from softgrip_calib.profile import MAX_N_LINKS

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
    from softgrip_vision.measure import MeasureSettings

    base = start.measure_settings() if start is not None else MeasureSettings()
    relief = base.finger_relief_mm if args.finger_relief is None else (
        None if args.finger_relief == "auto" else args.finger_relief)
    return MeasureSettings(base_end=args.base_end or base.base_end, finger_relief_mm=relief)


def run(args: argparse.Namespace) -> int:
    """Calibrate as ``args`` says, write the profile, print a report; 0 on success."""
    from softgrip_calib.fit import SkippedFrameWarning
    from softgrip_cli._pipeline import check_output_file

    inputs = _inputs(args)
    check_output_file(args.output, "-o", inputs, args.force)  # before a fit that may take minutes
    with warnings.catch_warnings():
        warnings.simplefilter("always", SkippedFrameWarning)
        warnings.showwarning = _print_warning
        profile, start_method = _fit(args) if args.fit else (_one_frame(args), None)
    from softgrip_calib.profile import save_profile

    save_profile(profile, args.output, inputs=inputs, force=args.force)
    if args.fit:
        _warn_if_free_closure_worse(profile, start_method)
    if args.json:
        report = {"output": str(args.output), "profile": profile.to_dict()}
        if args.fit:
            report.update(frames=_frame_report(profile), free_closure=_free_closure_report(profile, start_method))
        print(json.dumps(report))
    else:
        _print_summary(profile, args.output, start_method if args.fit else None)
    return 0


def _inputs(args: argparse.Namespace) -> list[Path]:
    """Every file the command reads: the frames' files and the start profile (output policy)."""
    from softgrip_cli._pipeline import frame_inputs

    frames = [args.closed, args.open_frame, *(args.fit or ()), *(args.empty or ())]
    return frame_inputs(*frames) + ([args.profile] if args.profile is not None else [])


def _one_frame(args: argparse.Namespace):
    from softgrip_calib.one_frame import one_frame_from_frames
    from softgrip_vision.frames import load_frame

    if args.closed is None or args.open_frame is None:
        raise SoftgripError("give CLOSED_FRAME and --open OPEN_FRAME for a one-frame calibration, or --fit OPEN "
                            "CLOSED [...] for least squares (see softgrip calibrate --help)")
    fit_only = [f"--{name.replace('_', '-')}" for name in ("profile", "empty", "base_offset", "method", "stiffness",
                                                           "base_compliance", "uniform")
                if getattr(args, name) not in (None, False)]
    if fit_only:
        raise SoftgripError(f"{', '.join(fit_only)} only apply to --fit")
    return one_frame_from_frames(load_frame(args.closed), load_frame(args.open_frame),
                                 args.n_links or DEFAULT_N_LINKS, label=f"{args.open_frame} + {args.closed}",
                                 camera_name=args.camera or "unspecified",
                                 names=(str(args.closed), str(args.open_frame)), measure=_measure_settings(args))


def _fit(args: argparse.Namespace):
    """The fitted profile, and the fit method of its start profile."""
    import dataclasses

    from softgrip_calib.fit import fit, load_observations, start_from_open_frame
    from softgrip_calib.one_frame import one_frame_from_frames
    from softgrip_calib.profile import load_profile
    from softgrip_vision.frames import load_frame

    if args.closed is not None or args.open_frame is not None:
        raise SoftgripError("CLOSED_FRAME and --open are for a one-frame calibration; with --fit give the frames "
                            "as pairs: --fit OPEN CLOSED [OPEN CLOSED ...]")
    if len(args.fit) % 2:
        raise SoftgripError(f"--fit needs frame pairs OPEN CLOSED, got {len(args.fit)} folders (an odd number)")
    if args.uniform and (args.stiffness or args.base_compliance):
        raise SoftgripError("--uniform keeps the uniform clamped finger; drop it, or drop --stiffness and "
                            "--base-compliance")
    pairs = list(zip(args.fit[0::2], args.fit[1::2]))
    empty, empty_given = (tuple(args.empty), True) if args.empty else (None, False)
    if args.profile is not None:
        start = load_profile(args.profile)
        n_links = start.fingers["left"].n_links
        if args.n_links is not None and args.n_links != n_links:
            raise SoftgripError(f"--n-links {args.n_links} differs from n_links = {n_links} in {args.profile}; "
                                f"drop --n-links, or calibrate a new profile with that N")
        if args.camera is not None:
            start = dataclasses.replace(start, camera={**start.camera, "name": args.camera})
        settings = start.segmentation_settings()
        if empty is None:
            empty = _recorded_free_closure(start, args.profile)
    elif empty is not None:
        # Start from the calibration pair's one-frame calibration (eqs. 4-5): L, r and W from its open
        # frame, Theta from its free closure; it also checks that the closed frame shows no object.
        n_links = args.n_links or DEFAULT_N_LINKS
        start = one_frame_from_frames(load_frame(empty[1]), load_frame(empty[0]), n_links,
                                      label=f"{empty[0]} + {empty[1]}", camera_name=args.camera or "unspecified",
                                      names=(str(empty[1]), str(empty[0])), measure=_measure_settings(args))
        settings = None
    else:
        n_links = args.n_links or DEFAULT_N_LINKS
        try:
            start = start_from_open_frame(load_frame(pairs[0][0]), n_links, camera_name=args.camera or "unspecified",
                                          measure=_measure_settings(args))
        except SoftgripError as err:  # the starting values come from the first open frame: name it
            message = str(err)
            raise type(err)(message if str(pairs[0][0]) in message else f"{pairs[0][0]}: {message}") from None
        settings = None
    estimator = resolve_estimator(args.method, start if args.profile is not None else None)
    mechanics_only = [flag for flag, on in (("--stiffness", args.stiffness),
                                            ("--base-compliance", args.base_compliance), ("--uniform", args.uniform))
                      if on]
    if mechanics_only and estimator.name != "mechanics":
        raise SoftgripError(f"{' and '.join(mechanics_only)} only change the mechanics estimate; add --method "
                            f"mechanics (the fit is going through the {estimator.name} estimate)")
    # Through the mechanics estimate without a stiffness flag, the pairs choose the stiffness model.
    select = estimator.name == "mechanics" and not mechanics_only
    parameters = ["theta_entire"] + [name for name, on in (("base_offset", args.base_offset),
                                                            ("stiffness_ratio", args.stiffness),
                                                            ("base_compliance", args.base_compliance)) if on]
    measure = _measure_settings(args, start)
    if empty is not None:  # the free-closure pair is one pair of the fit, not also an ordinary one
        pairs = [pair for pair in pairs if not _same_pair(pair, empty)]
    free, reason = (None, None) if empty is None else _free_closure(empty, settings, n_links, measure,
                                                                     must=empty_given)  # first: it may be refused
    observations, skipped = load_observations(pairs, settings, n_links, progress=True, measure=measure)
    if free is not None:
        observations.append(free)
    elif empty is not None and reason is not None:  # (a reason whenever the pair gave no observation)
        skipped.append({"frame": f"{empty[0]} + {empty[1]}", "reason": reason})
    elif args.profile is None:  # (a --profile's pair was looked for above, and its absence reported)
        print("softgrip calibrate: note: no pair of the gripper closed without an object in the fit, so nothing "
              "keeps it from making the free closure worse; add one with --empty OPEN CLOSED", file=sys.stderr)
    # A progress bar only on a terminal: its per-step callback keeps the solve out of the compilation
    # cache, so scripted runs (stderr not a terminal) compile once per machine instead of once per run.
    if select:
        from softgrip_calib.select import fit_stiffness_model

        fitted = fit_stiffness_model(observations, start, parameters, loss=args.loss, loss_scale_mm=args.loss_scale,
                                     estimator=estimator, skipped=skipped, progress=sys.stderr.isatty())
    else:
        fitted = fit(observations, start, parameters, loss=args.loss, loss_scale_mm=args.loss_scale,
                     estimator=estimator, skipped=skipped, progress=sys.stderr.isatty())
    # The start's method says what the free closure's start residual is (e.g. the one-frame calibration's).
    return dataclasses.replace(fitted, vision={**fitted.vision, **measure.to_dict()}), start.fit.method


def _same_pair(a: tuple[Path, Path], b: tuple[Path, Path]) -> bool:
    return all(Path(x).resolve() == Path(y).resolve() for x, y in zip(a, b))


def _free_closure(pair: tuple[Path, Path], settings, n_links: int, measure, must: bool):
    """(the free-closure Observation of ``pair`` (open, closed), None) or, when it cannot be used and
    ``must`` is False, (None, why) with a warning; when ``must``, the error names the pair."""
    from softgrip_calib.fit import SkippedFrameWarning, free_closure_observation
    from softgrip_vision.frames import load_frame

    label = f"{pair[0]} + {pair[1]}"
    try:
        return free_closure_observation(load_frame(pair[0]), load_frame(pair[1]), settings, n_links, label,
                                        measure=measure, closed_name=str(pair[1])), None
    except SoftgripError as err:
        if must:
            message = str(err) if any(str(p) in str(err) for p in pair) else f"{label}: {err}"
            raise type(err)(f"the --empty pair: {message}") from None
        warnings.warn(f"{label}: skipped: {err}", SkippedFrameWarning, stacklevel=2)
        return None, str(err)


def _recorded_free_closure(start, profile_path: Path) -> tuple[Path, Path] | None:
    """The (open, closed) folders of the free-closure pair the start profile records (a one-frame
    calibration's pair, or a fit's ``fit.free_closure``) when they exist, saying so on stderr; None
    with a warning naming them when they are missing, or a note when the profile names no frames."""
    fit = start.fit
    label = fit.free_closure or (fit.frames[0] if fit.method == "one-frame" and len(fit.frames) == 1 else None)
    splits = [] if label is None else [(label[:i], label[i + 3:]) for i in range(len(label)) if label[i:i + 3] == " + "]
    if not splits:
        print(one_line(f"softgrip calibrate: note: {profile_path} does not name the frames of a pair closed without "
                       f"an object; give them with --empty OPEN CLOSED so that the fit keeps the free closure"),
              file=sys.stderr)
        return None
    for open_name, closed_name in splits:
        for folder in (Path(), profile_path.parent):  # relative paths: from here, else next to the profile
            pair = (folder / open_name, folder / closed_name)
            if all(p.is_dir() for p in pair):
                print(one_line(f"softgrip calibrate: including the free-closure pair {pair[0]} + {pair[1]} that "
                               f"{profile_path} records (the gripper closed without an object) in the fit"),
                      file=sys.stderr)
                return pair
    missing = " and ".join(splits[0])
    print(one_line(f"softgrip calibrate: warning: {profile_path} records its free-closure pair {label}, but the "
                   f"folders {missing} do not exist (here or next to the profile): fitting without it, so the fit may "
                   f"make the closure without an object worse; give the pair with --empty OPEN CLOSED"),
          file=sys.stderr)
    return None


def _frame_report(profile) -> list[dict]:
    """Per frame pair of a fitted profile: label, residual RMS, residual RMS at the start values,
    mean joint error at joint N // 2 and at the tip (all mm; None where the profile has none), and
    whether it is the free-closure pair."""
    fit = profile.fit

    def at(values, i):
        return values[i] if values else None

    return [{"frame": label, "residual_rms_mm": at(fit.frame_residual_rms_mm, i),
             "start_residual_rms_mm": at(fit.frame_start_residual_rms_mm, i),
             "mid_error_mm": at(fit.frame_mid_error_mm, i), "tip_error_mm": at(fit.frame_tip_error_mm, i),
             "free_closure": label == fit.free_closure}
            for i, label in enumerate(fit.frames)]


def _free_closure_report(profile, start_method: str | None) -> dict | None:
    """The free-closure pair's residual RMS at the start and fitted (mm), or None without one."""
    fit = profile.fit
    if fit.free_closure is None or not fit.frame_start_residual_rms_mm:
        return None
    i = fit.frames.index(fit.free_closure)
    start, fitted = fit.frame_start_residual_rms_mm[i], fit.frame_residual_rms_mm[i]
    return {"frame": fit.free_closure, "start": start_method, "start_residual_rms_mm": start,
            "residual_rms_mm": fitted, "change_mm": fitted - start,
            "worse": fitted > start + FREE_CLOSURE_TOLERANCE_MM}


def _warn_if_free_closure_worse(profile, start_method: str | None) -> None:
    report = _free_closure_report(profile, start_method)
    if report is None or not report["worse"]:
        return
    start = "the one-frame calibration" if start_method == "one-frame" else "the start values"
    print(one_line(f"softgrip calibrate: warning: the fit made the free closure ({report['frame']}) worse: residual "
          f"RMS {report['residual_rms_mm']:.3f} mm against {report['start_residual_rms_mm']:.3f} mm at {start} "
          f"(+{report['change_mm']:.3f} mm). The pairs with objects pull Theta away from what the gripper shows "
          f"closed without an object: likely L, r or the base separation are measured wrong (check the frames' "
          f"measurement: the profile's vision.detected, --base-end, --finger-relief), or the estimate cannot "
          f"match both closures with one Theta (with --method geometric, try --method mechanics)"), file=sys.stderr)


def _print_summary(profile, output: Path, start_method: str | None = None) -> None:
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
    planes = profile.vision.get("plane_depth_mm")
    if planes:
        print(f"gripper plane {planes['open']:.2f} mm deep in the open frame, {planes['closed']:.2f} mm in the closed "
              f"one (millimetres from the {planes['used']} frame's)")
    if fit.method == "least-squares":
        _print_frames(profile, start_method)
    if fit.model_selection is not None:
        from softgrip_calib.select import describe_selection

        print("stiffness model (RMS joint distance of each pair predicted from the others, and fitted to all):")
        print("\n".join(describe_selection(fit.model_selection)))
    print(f"wrote {output}")


def _print_frames(profile, start_method: str | None) -> None:
    """One line per frame pair: residual RMS, mean joint error at joint N/2 and at the tip (mm); the
    free-closure pair also with its residual at the start."""
    rows = _frame_report(profile)
    if not rows or rows[0]["residual_rms_mm"] is None:
        return
    print("per frame pair (mm): residual RMS, mean joint error at joint N/2 and at the tip")
    free = _free_closure_report(profile, start_method)
    for row in rows:
        line = f"  {row['frame']}: RMS {row['residual_rms_mm']:.3f}"
        if row["mid_error_mm"] is not None:
            line += f", N/2 {row['mid_error_mm']:.3f}, tip {row['tip_error_mm']:.3f}"
        if row["free_closure"] and free is not None:
            start = "one-frame" if start_method == "one-frame" else "start"
            line += f"; free closure: {start} {free['start_residual_rms_mm']:.3f} -> fitted {free['residual_rms_mm']:.3f}"
        print(line)


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    from softgrip_cli import _pipeline

    if not _pipeline.quiet():
        print(f"softgrip calibrate: warning: {one_line(str(message))}", file=sys.stderr)
