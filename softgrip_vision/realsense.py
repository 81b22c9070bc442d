"""Frames from Intel RealSense cameras and recordings, through pyrealsense2.

Every capture ends as frame folders (see :mod:`softgrip_vision.frames`): colour in RGB order, depth
registered to the colour image in units of the device's depth scale, and the colour stream's
intrinsics. pyrealsense2 is optional (``pip install 'softgrip-jax[realsense]'``) and imported on
first use.

Recordings are read in one non-real-time pass with a callback on each sensor, and depth and
colour frames are paired afterwards by timestamp. ``rs.pipeline`` playback was measured (2.59)
to skip the first framesets, to pair depth with stale colour frames, to stall on short recordings
and to crash when restarted many times; a single pass with callbacks delivered every frame in
600 of 600 runs.
"""

from __future__ import annotations

import ctypes
import importlib
import os
import re
import sqlite3
import shutil
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from softgrip_base.errors import SoftgripError
from softgrip_vision.frames import (DISTORTION_MODELS, Frame, FrameError, Intrinsics, _f32, next_frame_dir,
                                    save_frame)

RECORDING_SUFFIXES = (".db3", ".bag")
_CAMERA_WAIT_MS = 5000


class CameraError(SoftgripError):
    """A camera or recording that cannot be used; the message names it and the fix."""


class RecordingDamagedError(CameraError):
    """A recording that delivered fewer depth frames than its container holds.

    Raised after the frames that could be read are written (``written``); ``lost`` lists the depth
    frame numbers the container records but playback did not deliver (empty when the container's
    index itself cannot be read, see ``message``).
    """

    def __init__(self, message: str, written: list[Path], lost: list[int]) -> None:
        super().__init__(message)
        self.written, self.lost = written, lost


_FRAME_NUMBER = re.compile(rb"Frame number=(\d+)")


def recording_depth_frames(path: str | os.PathLike[str]) -> list[int] | None:
    """The depth frame numbers a ``.db3`` recording's container holds, read from its SQLite index
    (the metadata message stored with every depth image), in recording order. None for a legacy
    ``.bag`` (no index read here).

    Raises:
        CameraError: the ``.db3`` container's index cannot be read (the file is damaged).
    """
    path = Path(path)
    if path.suffix.lower() != ".db3":
        return None
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            topics = dict(db.execute("SELECT id, name FROM topics").fetchall())
            meta = [i for i, name in topics.items() if re.search(r"/Depth_\d+/image/metadata$", name)]
            data = [i for i, name in topics.items() if re.search(r"/Depth_\d+/image/data", name)]
            numbers = []
            for topic in meta[:1]:
                for (blob,) in db.execute("SELECT data FROM messages WHERE topic_id = ? ORDER BY timestamp", (topic,)):
                    match = _FRAME_NUMBER.search(bytes(blob))
                    if match:
                        numbers.append(int(match.group(1)))
            count = sum(db.execute("SELECT COUNT(*) FROM messages WHERE topic_id = ?", (t,)).fetchone()[0]
                        for t in data[:1])
        finally:
            db.close()
    except sqlite3.Error as err:
        raise CameraError(f"{path}: the recording's index cannot be read ({err}): the file is damaged") from None
    if len(numbers) != count:  # metadata without frame numbers: count the images instead
        numbers = list(range(count))
    return numbers


@dataclass(frozen=True)
class DeviceInfo:
    """A connected RealSense device."""

    name: str
    serial: str
    firmware: str


def import_realsense() -> ModuleType:
    """Import pyrealsense2, first loading the libusb of the ``libusb-package`` wheel if present.

    pyrealsense2's wheel needs ``libusb-1.0.so.0`` but does not ship it; loading the wheel's copy
    with ``RTLD_GLOBAL`` lets the import resolve it without a system package.

    Example:
        >>> import_realsense().__name__
        'pyrealsense2'
    """
    try:
        import libusb_package

        library = libusb_package.get_library_path()
        if library is not None:
            ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # the system's libusb may still be there; the import below tells
    try:  # (by name: pyrealsense2 ships no type information, and is used as a ModuleType anyway)
        pyrealsense2 = importlib.import_module("pyrealsense2")
    except ImportError as err:
        raise CameraError(
            f"cannot import pyrealsense2 ({err}): install the RealSense extra with "
            f"pip install 'softgrip-jax[realsense]' (pyrealsense2 and libusb-package), or install "
            f"Debian's libusb-1.0-0 (apt-get install libusb-1.0-0)"
        ) from err
    return pyrealsense2


def _distortion(intr) -> tuple[str, tuple[float, ...]]:
    """The colour stream's lens distortion as ``Intrinsics`` keeps it: pyrealsense2's model name and
    its five coefficients (``"none"`` when they are all zero)."""
    coeffs = tuple(_f32(c) for c in getattr(intr, "coeffs", ()))
    name = str(getattr(intr, "model", "none")).rsplit(".", 1)[-1]
    if not any(coeffs) or name not in DISTORTION_MODELS:
        if any(coeffs):
            warnings.warn(f"the camera's lens distortion {name!r} is not one softgrip knows; recorded without it")
        return "none", ()
    return name, coeffs[:5] if name != "kannala_brandt4" else coeffs[:4]


def list_devices() -> list[DeviceInfo]:
    """The connected RealSense devices (empty list when there is none).

    Example (each entry is a ``DeviceInfo`` with the camera's name and serial number):
        >>> isinstance(list_devices(), list)
        True
    """
    rs = import_realsense()
    return [_device_info(rs, device) for device in rs.context().query_devices()]


def capture_from_camera(
    out_root: str | os.PathLike[str],
    *,
    serial: str | None = None,
    width: int = 640,
    height: int = 480,
    fps: int = 30,
    count: int = 1,
    warmup: int = 15,
) -> list[Path]:
    """Capture ``count`` frames from a RealSense camera into new ``out_root/frame_NNNN`` folders.

    Depth (z16) and colour (rgb8) stream at ``width`` x ``height`` and ``fps``; depth is aligned to
    colour with ``rs.align``. The first ``warmup`` framesets are dropped while auto-exposure
    settles. ``serial`` picks a device (default: the first one found). Returns the folders written.

    Example (needs a connected camera, so the doctest run skips it; ``capture_from_recording`` is the
    same path from a recording, with a doctested example):
        >>> folders = capture_from_camera("frames", count=2)  # doctest: +SKIP
        >>> [f.name for f in folders]  # doctest: +SKIP
        ['frame_0000', 'frame_0001']
    """
    for name, value, least in (("width", width, 1), ("height", height, 1), ("fps", fps, 1),
                               ("count", count, 1), ("warmup", warmup, 0)):
        if not isinstance(value, int) or value < least:
            raise CameraError(f"{name} must be an integer >= {least}, got {value!r}")
    rs = import_realsense()
    context = rs.context()
    devices = [_device_info(rs, device) for device in context.query_devices()]
    if not devices:
        raise CameraError("no RealSense camera found: connect one (USB 3 port and cable), check "
                          "it appears in realsense-viewer, or read a recording with --bag FILE")
    if serial is None:
        serial = devices[0].serial
    elif serial not in {device.serial for device in devices}:
        found = ", ".join(f"{d.serial} ({d.name})" for d in devices)
        raise CameraError(f"no RealSense camera with serial {serial}; connected: {found}")
    config = rs.config()
    config.enable_device(serial)
    config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
    config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
    pipeline = rs.pipeline(context)
    if not config.can_resolve(pipeline):
        raise CameraError(f"camera {serial} cannot stream depth and colour at {width}x{height} "
                          f"and {fps} fps: try --width 640 --height 480 --fps 30")
    try:
        profile = pipeline.start(config)
    except RuntimeError as err:
        raise CameraError(f"cannot start camera {serial} ({err}): close other programs using it "
                          f"(realsense-viewer, ROS nodes) and try again") from err
    try:
        frames = _grab(rs, pipeline, profile, serial, count, warmup)
    finally:
        pipeline.stop()
    return _save_frames(frames, out_root)


def _grab(rs: ModuleType, pipeline: Any, profile: Any, serial: str, count: int,
          warmup: int) -> list[Frame]:
    """``count`` frames from a started pipeline; no pyrealsense2 frame outlives this call."""
    depth_scale = profile.get_device().first_depth_sensor().get_depth_scale()
    align = _registration(rs, profile.get_stream(rs.stream.depth),
                          profile.get_stream(rs.stream.color))
    frames: list[Frame] = []
    last_number = None
    with tqdm(total=warmup + count, desc=f"camera {serial}", unit="frame", disable=None) as bar:
        for _ in range(warmup):
            _wait(pipeline, serial)
            bar.update()
        while len(frames) < count:
            frameset = _wait(pipeline, serial)
            depth, color = frameset.get_depth_frame(), frameset.get_color_frame()
            # the pipeline fills a missing stream with its previous frame: skip such framesets
            if not _in_sync(depth, color) or depth.get_frame_number() == last_number:
                continue
            last_number = depth.get_frame_number()
            if align is not None:
                frameset = align.process(frameset)
                depth, color = frameset.get_depth_frame(), frameset.get_color_frame()
            try:
                frames.append(_to_frame(rs, depth, color, depth_scale))
            except FrameError as err:
                raise CameraError(f"camera {serial}: {err}") from None
            bar.update()
    return frames


def capture_from_recording(
    path: str | os.PathLike[str],
    out_root: str | os.PathLike[str],
    *,
    count: int | None = None,
    stall_timeout: float = 10.0,
    allow_partial: bool = False,
) -> list[Path]:
    """Write the frames of a recording (``.db3``, or legacy ``.bag``) as ``out_root/frame_NNNN``.

    Nothing is lost silently: for a ``.db3`` the depth frames its container holds are counted (its
    SQLite index, :func:`recording_depth_frames`), and when playback delivers fewer (a damaged
    file), the frames that could be read are written and :class:`RecordingDamagedError` names the
    lost frame numbers; with ``allow_partial`` a warning says the same instead. A legacy ``.bag`` is
    not counted.

    Writes the first ``count`` frames of the recording in recording order (all by default). Each
    depth frame is paired with the colour frame nearest in time, if that is within half a frame
    period (librealsense's own sync rule), and aligned to it with ``rs.align`` unless the depth
    stream is already registered to colour. Depth frames with no readings or no colour partner
    are skipped with a warning. Decoded frames are held in memory until written: pass ``count``
    for long recordings. Raises :class:`CameraError` if playback delivers nothing for
    ``stall_timeout`` seconds.

    Example: see :func:`write_recording`.
    """
    rs = import_realsense()
    path = Path(path)
    if path.suffix.lower() not in RECORDING_SUFFIXES:
        raise CameraError(f"{path} is not a RealSense recording: expected a .db3 file (or a "
                          f"legacy .bag), as written by realsense-viewer")
    from softgrip_base.input_guard import check_user_file

    check_user_file(path, what="the recording", error=CameraError,
                    missing="the recording does not exist: check the path")
    if count is not None and (not isinstance(count, int) or count < 1):
        raise CameraError(f"count must be an integer >= 1, got {count!r}")
    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as err:
        raise CameraError(f"{path} is not a readable RealSense recording ({err}): record it "
                          f"again, or check that the copy is complete") from err
    try:
        claimed, index_problem = recording_depth_frames(path), None
    except CameraError as err:
        claimed, index_problem = None, str(err)
    seen: list[int] = []
    frames = _read_recording(rs, device, path, count, stall_timeout, seen)
    lost = [] if claimed is None else sorted(set(claimed) - set(seen))
    if count is not None and len(frames) >= count:
        lost = []  # what was asked for was read; the rest of the recording was not needed
    if not frames and not lost and index_problem is None:
        raise CameraError(f"{path} has no frame with depth readings and a colour frame in sync")
    written = _save_frames(frames, out_root) if frames else []
    if lost or index_problem:
        total = f"{len(claimed)} depth frames" if claimed is not None else "an unknown number of frames"
        what = (f"{path}: the recording holds {total} but only {len(seen)} could be read; lost: "
                f"{', '.join(map(str, lost[:20]))}{' ...' if len(lost) > 20 else ''}" if lost else index_problem)
        message = (f"{what}. Wrote {len(written)} frame(s); the recording is damaged: record it again, or pass "
                   f"--allow-partial (allow_partial=True) to accept the frames that could be read")
        if not allow_partial:
            raise RecordingDamagedError(message, written, lost)
        warnings.warn(message, stacklevel=2)
    return written


def _read_recording(rs: ModuleType, device: Any, path: Path, count: int | None,
                    stall_timeout: float, seen: list[int] | None = None) -> list[Frame]:
    """Play ``device`` (a loaded recording) once, as fast as it decodes, and pair its frames;
    the numbers of the depth frames playback delivered are appended to ``seen``."""
    sensors = device.query_sensors()
    chosen: dict[Any, tuple[int, Any]] = {}  # stream type -> (sensor index, profile)
    for index, sensor in enumerate(sensors):
        for profile in sensor.get_stream_profiles():
            if profile.stream_type() in (rs.stream.depth, rs.stream.color):
                chosen.setdefault(profile.stream_type(), (index, profile))
    for stream, label in ((rs.stream.depth, "depth"), (rs.stream.color, "colour")):
        if stream not in chosen:
            raise CameraError(f"{path} has no {label} stream: record both depth and colour")
    (depth_index, depth_profile), (_, color_profile) = (chosen[rs.stream.depth],
                                                        chosen[rs.stream.color])
    try:
        depth_scale = sensors[depth_index].as_depth_sensor().get_depth_scale()
    except RuntimeError as err:
        raise CameraError(f"{path} records no depth scale ({err}): record it again") from err
    half_period_ms = 500.0 / max(min(depth_profile.fps(), color_profile.fps()), 1)
    collector = _Collector(rs, count, half_period_ms)
    playback = device.as_playback()
    playback.set_real_time(False)
    finished = threading.Event()
    playback.set_status_changed_callback(
        lambda status: finished.set() if status == rs.playback_status.stopped else None)
    profiles: dict[int, list[Any]] = {}  # D405 streams depth and colour from one sensor
    for index, profile in chosen.values():
        profiles.setdefault(index, []).append(profile)
    opened = [sensors[index] for index in profiles]
    for sensor, sensor_profiles in zip(opened, profiles.values()):
        sensor.open(sensor_profiles)
    try:
        playback.pause()  # until every sensor is started, or the first frames go nowhere
        for sensor in opened:
            sensor.start(collector)
        playback.resume()
        try:
            _wait_for_playback(finished, collector, stall_timeout, path)
        finally:
            for sensor in opened:
                sensor.stop()
        if seen is not None:
            seen.extend(collector.seen)
        return _pair(rs, collector, path, depth_scale,
                     _registration(rs, depth_profile, color_profile))
    finally:
        collector.clear()  # pyrealsense2 frames must not outlive their sensors
        for sensor in opened:
            sensor.close()


class _Collector:
    """Sensor callback keeping the depth and colour frames a capture needs.

    With ``count``, keeps the first ``count`` depth frames that have readings and the colour
    frames up to half a period after the last of them; the rest of the recording plays through.
    """

    def __init__(self, rs: ModuleType, count: int | None, half_period_ms: float) -> None:
        self.rs, self.count, self.half_period_ms = rs, count, half_period_ms
        self.depth: list[Any] = []
        self.color: list[Any] = []
        self.empty: list[int] = []  # depth frame numbers without readings
        self.seen: list[int] = []  # every depth frame number delivered
        self.arrived = 0
        self.lock = threading.Lock()

    def __call__(self, frame: Any) -> None:
        with self.lock:
            self.arrived += 1
            full = self.count is not None and len(self.depth) >= self.count
            if frame.get_profile().stream_type() == self.rs.stream.depth:
                self.seen.append(frame.get_frame_number())
                if full:
                    return
                if not np.asanyarray(frame.get_data()).any():
                    self.empty.append(frame.get_frame_number())
                    return
                frame.keep()
                self.depth.append(frame)
            elif not full or frame.get_timestamp() < (self.depth[-1].get_timestamp()
                                                      + self.half_period_ms):
                frame.keep()
                self.color.append(frame)

    def clear(self) -> None:
        with self.lock:
            self.depth.clear()
            self.color.clear()


def _wait_for_playback(finished: threading.Event, collector: _Collector, stall_timeout: float,
                       path: Path) -> None:
    with tqdm(desc=f"reading {path.name}", unit="frame", disable=None) as bar:
        last_arrived, last_change = 0, time.monotonic()
        while not finished.wait(0.05):
            if collector.arrived != last_arrived:
                bar.update(collector.arrived - last_arrived)
                last_arrived, last_change = collector.arrived, time.monotonic()
            elif time.monotonic() - last_change > stall_timeout:
                raise CameraError(f"{path}: playback delivered nothing for {stall_timeout:g} s "
                                  f"after {last_arrived} frame(s); the recording may be damaged")
        bar.update(collector.arrived - last_arrived)


def _pair(rs: ModuleType, collector: _Collector, path: Path, depth_scale: float,
          align: Any | None) -> list[Frame]:
    """A frame per kept depth frame and the colour frame nearest in time, if within half a
    frame period; ``align`` (``rs.align`` or None) registers depth to colour."""
    for number in collector.empty:
        warnings.warn(f"{path}: skipped depth frame {number}: it has no depth readings",
                      stacklevel=4)
    color_times = np.array([color.get_timestamp() for color in collector.color])
    compose = _composer(rs) if align is not None else None
    frames = []
    for depth in collector.depth:
        gaps = np.abs(color_times - depth.get_timestamp())
        if not gaps.size or gaps.min() >= collector.half_period_ms:
            warnings.warn(f"{path}: skipped depth frame {depth.get_frame_number()}: no colour "
                          f"frame within half a frame period", stacklevel=4)
            continue
        color = collector.color[int(gaps.argmin())]
        if compose is not None and align is not None:
            frameset = align.process(compose(depth, color))
            depth, color = frameset.get_depth_frame(), frameset.get_color_frame()
        try:
            frames.append(_to_frame(rs, depth, color, depth_scale))
        except FrameError as err:
            warnings.warn(f"{path}: skipped depth frame {depth.get_frame_number()}: {err}",
                          stacklevel=4)
    return frames


def _composer(rs: ModuleType) -> Callable[[Any, Any], Any]:
    """(depth frame, colour frame) -> frameset, the input ``rs.align`` needs."""
    queue = rs.frame_queue(1)
    pair: list[Any] = []
    block = rs.processing_block(
        lambda frame, source: source.frame_ready(source.allocate_composite_frame(pair)))
    block.start(queue)

    def compose(depth: Any, color: Any) -> Any:
        pair[:] = [depth, color]
        block.invoke(depth)
        pair.clear()
        return queue.wait_for_frame(_CAMERA_WAIT_MS).as_frameset()

    return compose


def write_recording(
    path: str | os.PathLike[str],
    frames: Sequence[Frame],
    name: str = "softgrip synthetic",
    fps: int = 30,
) -> Path:
    """Write ``frames`` as a RealSense recording (``.db3``) that plays like a real camera's.

    A ``rs.software_device`` with a depth (z16) and a colour (rgb8) stream, both with the frames'
    intrinsics, identity extrinsics between them and the frames' depth scale as ``depth_units``,
    is recorded while the frames are injected at ``fps``. All frames must share one
    :class:`Intrinsics`. Pixels play back bit-exact; intrinsics and depth scale are stored as
    float32. Written atomically (temporary sibling, then rename); never overwrites ``path``.

    Example (a recording of two sample frames, written and read back; no camera needed):
        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np
        >>> import softgrip_vision
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"
        >>> frames = [load_frame(data / name) for name in ("circle_open", "square_open")]
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     recording = write_recording(Path(folder) / "scene.db3", frames)
        ...     written = capture_from_recording(recording, Path(folder) / "frames")
        ...     again = [load_frame(p) for p in written]
        >>> [p.name for p in written], all(np.array_equal(a.depth, b.depth) for a, b in zip(frames, again))
        (['frame_0000', 'frame_0001'], True)
    """
    rs = import_realsense()
    path = Path(path)
    if path.suffix.lower() != ".db3":
        raise CameraError(f"{path}: recordings are written as .db3 (librealsense 2.58 and later "
                          f"cannot write .bag); give a name ending in .db3")
    _refuse_existing(path)
    if not frames:
        raise FrameError("write_recording needs at least one frame")
    for index, frame in enumerate(frames):
        if not isinstance(frame, Frame):
            raise FrameError(f"frames[{index}] is a {type(frame).__name__}, not a Frame")
        if frame.intrinsics != frames[0].intrinsics:
            raise FrameError(f"frames[{index}] has intrinsics {frame.intrinsics} but frames[0] "
                             f"has {frames[0].intrinsics}: a recording has one stream profile")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.partial"
    tmp.mkdir()
    try:
        _record(rs, tmp / path.name, frames, name, fps)
        _refuse_existing(path)
        os.rename(tmp / path.name, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def _record(rs: ModuleType, path: Path, frames: Sequence[Frame], name: str, fps: int) -> None:
    intrinsics = frames[0].intrinsics
    device = rs.software_device()
    device.register_info(rs.camera_info.name, name)
    depth_sensor = device.add_sensor("Depth")
    color_sensor = device.add_sensor("Color")
    depth_profile = depth_sensor.add_video_stream(
        _video_stream(rs, rs.stream.depth, rs.format.z16, 2, 0, intrinsics, fps))
    color_profile = color_sensor.add_video_stream(
        _video_stream(rs, rs.stream.color, rs.format.rgb8, 3, 1, intrinsics, fps))
    depth_sensor.add_read_only_option(rs.option.depth_units, intrinsics.depth_scale)
    identity = rs.extrinsics()
    identity.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    identity.translation = [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(color_profile, identity)
    streams = ((depth_sensor, depth_profile, "depth"), (color_sensor, color_profile, "color"))
    recorder = rs.recorder(str(path), device)  # before the sensors open, or nothing is recorded
    sink = rs.frame_queue(1)
    for sensor, profile, _ in streams:
        sensor.open(profile)
    for sensor, _, _ in streams:
        sensor.start(sink)
    try:
        for number, frame in enumerate(tqdm(frames, desc=f"writing {path.name}", unit="frame",
                                            disable=None)):
            for sensor, profile, field in streams:
                sensor.on_video_frame(_software_frame(rs, profile, getattr(frame, field),
                                                      number, fps))
    finally:
        for sensor, _, _ in streams:
            sensor.stop()
        for sensor, _, _ in streams:
            sensor.close()
        del recorder  # finalises the file


def _video_stream(rs: ModuleType, stream: Any, fmt: Any, bpp: int, uid: int,
                  intrinsics: Intrinsics, fps: int) -> Any:
    rs_intrinsics = rs.intrinsics()
    rs_intrinsics.width, rs_intrinsics.height = intrinsics.width, intrinsics.height
    rs_intrinsics.fx, rs_intrinsics.fy = intrinsics.fx, intrinsics.fy
    rs_intrinsics.ppx, rs_intrinsics.ppy = intrinsics.ppx, intrinsics.ppy
    # The lens distortion too, so that capture from the recording gives it back (a model pyrealsense2
    # has no name for is written as none).
    model = getattr(rs.distortion, intrinsics.model, None)
    rs_intrinsics.model = model if model is not None else rs.distortion.none
    rs_intrinsics.coeffs = (list(intrinsics.coeffs) + [0.0] * 5)[:5] if model is not None else [0.0] * 5
    video = rs.video_stream()
    video.type, video.index, video.uid = stream, 0, uid
    video.width, video.height, video.fps = intrinsics.width, intrinsics.height, fps
    video.bpp, video.fmt, video.intrinsics = bpp, fmt, rs_intrinsics
    return video


def _software_frame(rs: ModuleType, profile: Any, pixels: np.ndarray, number: int,
                    fps: int) -> Any:
    frame = rs.software_video_frame()
    frame.pixels = np.ascontiguousarray(pixels)
    frame.bpp = pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1)
    frame.stride = pixels.shape[1] * frame.bpp
    frame.timestamp = number * 1000.0 / fps
    frame.domain = rs.timestamp_domain.hardware_clock
    frame.frame_number = number
    frame.profile = profile.as_video_stream_profile()
    return frame


def _registration(rs: ModuleType, depth_profile: Any, color_profile: Any) -> Any | None:
    """``rs.align`` to colour, or None when depth is already registered to colour.

    Registered means equal intrinsics and identity extrinsics, as in recordings made by
    :func:`write_recording`. ``rs.align`` would still resample such depth (each pixel spreads
    over its neighbours, nearest reading wins), so it is skipped.
    """
    depth = depth_profile.as_video_stream_profile()
    color = color_profile.as_video_stream_profile()
    if _intrinsics_key(depth.get_intrinsics()) == _intrinsics_key(color.get_intrinsics()):
        try:
            extrinsics = depth.get_extrinsics_to(color)
        except RuntimeError:
            extrinsics = None
        if extrinsics is not None and list(extrinsics.rotation) == [1, 0, 0, 0, 1, 0, 0, 0, 1] \
                and not any(extrinsics.translation):
            return None
    return rs.align(rs.stream.color)


def _intrinsics_key(intrinsics: Any) -> tuple[Any, ...]:
    return (intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.ppx,
            intrinsics.ppy, intrinsics.model, tuple(intrinsics.coeffs))


def _in_sync(depth: Any, color: Any) -> bool:
    """librealsense's sync rule: timestamps closer than half a period of the slower stream."""
    if not depth or not color:
        return False
    fps = max(min(depth.get_profile().fps(), color.get_profile().fps()), 1)
    return abs(depth.get_timestamp() - color.get_timestamp()) < 500.0 / fps


def _to_frame(rs: ModuleType, depth: Any, color: Any, depth_scale: float) -> Frame:
    """A :class:`Frame` (numpy copies) from registered depth and colour frames."""
    if depth.get_profile().format() != rs.format.z16:
        raise CameraError(f"depth stream format {depth.get_profile().format()} is not z16")
    intr = color.get_profile().as_video_stream_profile().get_intrinsics()
    model, coeffs = _distortion(intr)
    intrinsics = Intrinsics(width=intr.width, height=intr.height, fx=_f32(intr.fx),
                            fy=_f32(intr.fy), ppx=_f32(intr.ppx), ppy=_f32(intr.ppy),
                            depth_scale=_f32(depth_scale), model=model, coeffs=coeffs)
    return Frame(color=_rgb(rs, color), depth=np.array(depth.get_data(), dtype=np.uint16),
                 intrinsics=intrinsics)


def _rgb(rs: ModuleType, color: Any) -> np.ndarray:
    """(H, W, 3) uint8 RGB copy of a colour frame."""
    conversions = {rs.format.rgb8: None, rs.format.bgr8: cv2.COLOR_BGR2RGB,
                   rs.format.rgba8: cv2.COLOR_RGBA2RGB, rs.format.bgra8: cv2.COLOR_BGRA2RGB,
                   rs.format.yuyv: cv2.COLOR_YUV2RGB_YUYV, rs.format.uyvy: cv2.COLOR_YUV2RGB_UYVY}
    fmt = color.get_profile().format()
    if fmt not in conversions:
        raise CameraError(f"colour stream format {fmt} is not supported: record colour as "
                          f"rgb8, bgr8, rgba8, bgra8, yuyv or uyvy")
    pixels = np.asanyarray(color.get_data())
    code = conversions[fmt]
    return np.array(pixels, dtype=np.uint8) if code is None else cv2.cvtColor(pixels, code)




def _save_frames(frames: Sequence[Frame], out_root: str | os.PathLike[str]) -> list[Path]:
    root = Path(out_root)
    if root.exists() and not root.is_dir():
        raise FrameError(f"output {root} is a file: give a folder for the frames")
    return [save_frame(frame, next_frame_dir(root)) for frame in frames]


def _wait(pipeline: Any, serial: str) -> Any:
    ok, frameset = pipeline.try_wait_for_frames(_CAMERA_WAIT_MS)
    if not ok:
        raise CameraError(f"camera {serial} sent no frames for {_CAMERA_WAIT_MS / 1000:g} s: "
                          f"check the USB connection (USB 3) and try again")
    return frameset


def _device_info(rs: ModuleType, device: Any) -> DeviceInfo:
    def info(key: Any) -> str:
        return device.get_info(key) if device.supports(key) else ""

    return DeviceInfo(name=info(rs.camera_info.name), serial=info(rs.camera_info.serial_number),
                      firmware=info(rs.camera_info.firmware_version))


def _refuse_existing(path: Path) -> None:
    if os.path.lexists(path):
        raise CameraError(f"{path} already exists: recordings are never overwritten; choose "
                          f"another name or remove it first")
