"""``softgrip capture``: frame folders from a RealSense camera or a recording."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

from softgrip_vision.realsense import CameraError, RecordingDamagedError, capture_from_camera, capture_from_recording
from softgrip_cli._args import positive_int

EPILOG = """\
examples:
  softgrip capture --out frames                      one frame from the first camera
  softgrip capture --out frames --count 5 --serial 123456789012
  softgrip capture --out frames --width 848 --height 480 --fps 15
  softgrip capture --out frames --bag scene.db3      every frame of a recording
  softgrip capture --out frames --bag scene.bag --count 3 --json

Each frame is a new folder DIR/frame_0000, frame_0001, ... (the first free names) holding
color.png (8-bit RGB), depth.png (16-bit, units of depth_scale metres, 0 = no reading,
aligned to colour) and intrinsics.json (colour intrinsics and depth_scale). Existing folders
are never overwritten. A .db3 recording's frames are counted from its container: if playback
delivers fewer (a damaged file), the readable frames are written, the lost frame numbers named,
and the command exits with 2 (0 with --allow-partial). Needs pyrealsense2: pip install 'softgrip-jax[realsense]'.
"""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``capture`` on the ``softgrip`` sub-command parsers."""
    parser = subparsers.add_parser(
        "capture",
        help="capture frames from a RealSense camera or a recording",
        description="Capture RGB-D frames from an Intel RealSense camera, or extract them from a "
                    "recording (.db3, or legacy .bag), as frame folders.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-o", "--output", "--out", dest="out", required=True, type=Path, metavar="DIR",
                        help="folder to write the frame folders into (created if missing)")
    parser.add_argument("--bag", type=Path, metavar="FILE",
                        help="read this recording (.db3, or legacy .bag) instead of a camera")
    parser.add_argument("--serial", help="camera serial number (default: the first camera)")
    parser.add_argument("--width", type=positive_int, metavar="PX",
                        help="camera stream width (default: 640)")
    parser.add_argument("--height", type=positive_int, metavar="PX",
                        help="camera stream height (default: 480)")
    parser.add_argument("--fps", type=positive_int, help="camera frame rate (default: 30)")
    parser.add_argument("--count", type=positive_int, metavar="N",
                        help="number of frames (default: 1 from a camera, all of a recording)")
    parser.add_argument("--allow-partial", action="store_true",
                        help="with --bag, accept a damaged recording: write the frames that can be read, warn "
                             "about the lost ones and exit 0 (default: exit 2 naming the lost frames)")
    parser.add_argument("--json", action="store_true",
                        help='print {"frames": [folder, ...]} on stdout')
    # Neither the core nor the compilation cache: capture does not import JAX (softgrip_cli._main).
    parser.set_defaults(func=run, uses_jax=False)
    return parser


def run(args: argparse.Namespace) -> int:
    """Capture as ``args`` says, print the folders written; 0 on success."""
    from softgrip_base.atomic_write import probe_folder

    probe_folder(args.out, what=f"-o {args.out}")  # before the camera or the recording: a read-only folder
    if args.bag is not None:
        camera_only = [f"--{name}" for name in ("serial", "width", "height", "fps")
                       if getattr(args, name) is not None]
        if camera_only:
            raise CameraError(f"{', '.join(camera_only)} apply to a camera, not to --bag "
                              f"{args.bag}: a recording keeps the settings it was made with")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("always")
                warnings.showwarning = _ignore_warning if getattr(args, "quiet", False) else _print_warning
                paths = capture_from_recording(args.bag, args.out, count=args.count,
                                               allow_partial=args.allow_partial)
        except RecordingDamagedError as err:
            _print_paths(err.written, args.json, lost=err.lost)  # what was written is still reported
            raise
    elif args.allow_partial:
        raise CameraError("--allow-partial applies to --bag (a recording), not to a camera")
    else:
        paths = capture_from_camera(
            args.out,
            serial=args.serial,
            width=args.width or 640,
            height=args.height or 480,
            fps=args.fps or 30,
            count=args.count or 1,
        )
    _print_paths(paths, args.json)
    return 0


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    from softgrip_base.input_guard import one_line

    print(f"softgrip capture: warning: {one_line(str(message))}", file=sys.stderr)


def _ignore_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """-q: warnings are not printed."""


def _print_paths(paths, as_json: bool, lost=None) -> None:
    if as_json:
        record: dict[str, Any] = {"frames": [str(path) for path in paths]}
        if lost is not None:
            record.update(complete=False, lost_frame_numbers=list(lost))
        print(json.dumps(record))
    else:
        for path in paths:
            print(path)
