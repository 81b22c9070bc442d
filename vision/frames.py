"""RGB-D frames in memory and on disk (README: "File formats").

A frame on disk is a folder of three files::

    color.png        8-bit, 3 channels (stored BGR, as every PNG written by OpenCV)
    depth.png        16-bit, 1 channel, in units of ``depth_scale`` metres, 0 = no reading
    intrinsics.json  {"width", "height", "fx", "fy", "ppx", "ppy", "depth_scale"}

The intrinsics are those of the colour camera, with pyrealsense2's names: ``fx``/``fy`` focal
lengths and ``ppx``/``ppy`` principal point in pixels, ``depth_scale`` in metres per depth unit.
The depth image is registered to the colour image (pixel (u, v) of both sees the same point).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import stat
import uuid
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from softgrip_jax._errors import SoftgripError
from vision import user_json

COLOR_FILE = "color.png"
DEPTH_FILE = "depth.png"
INTRINSICS_FILE = "intrinsics.json"


class FrameError(SoftgripError):
    """A frame (folder, file or array) that cannot be used; the message names it and the fix."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera and the depth unit.

    ``width``/``height`` in pixels; ``fx``, ``fy``, ``ppx``, ``ppy`` in pixels (x right, y down,
    origin at the centre of the top-left pixel, as pyrealsense2); ``depth_scale`` in metres per
    unit of the depth image (RealSense D4xx default: 0.001).
    """

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    depth_scale: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not _is_int(value) or value <= 0:
                raise FrameError(f"{name} must be a positive integer (pixels), got {value!r}")
        for name in ("fx", "fy", "ppx", "ppy", "depth_scale"):
            value = getattr(self, name)
            if not _is_number(value) or not math.isfinite(value):
                raise FrameError(f"{name} must be a finite number, got {value!r}")
        for name in ("fx", "fy", "depth_scale"):
            if getattr(self, name) <= 0:
                raise FrameError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in _FIELDS:  # plain Python numbers, so equality and JSON behave
            convert = int if name in ("width", "height") else float
            object.__setattr__(self, name, convert(getattr(self, name)))

    def to_dict(self) -> dict[str, int | float]:
        """The JSON object of ``intrinsics.json``."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any, source: str = "intrinsics") -> Intrinsics:
        """Build from a JSON object; errors name ``source`` (usually the file) and the key.

        Keys other than the seven fields are ignored. Integers are accepted for the float fields.
        """
        if not isinstance(d, dict):
            raise FrameError(
                f"{source}: expected a JSON object with keys {', '.join(_FIELDS)}, "
                f"got {type(d).__name__}"
            )
        missing = [key for key in _FIELDS if key not in d]
        if missing:
            raise FrameError(
                f"{source}: missing key(s) {', '.join(missing)}; "
                f"intrinsics need {', '.join(_FIELDS)} (pyrealsense2 names)"
            )
        for key in ("width", "height"):
            if not _is_int(d[key]):
                raise FrameError(f"{source}: {key} must be an integer, got {d[key]!r}")
        for key in ("fx", "fy", "ppx", "ppy", "depth_scale"):
            if not _is_number(d[key]):
                raise FrameError(f"{source}: {key} must be a number, got {d[key]!r}")
        try:
            return cls(**{key: d[key] for key in _FIELDS})
        except FrameError as err:
            raise FrameError(f"{source}: {err}") from None


_FIELDS = ("width", "height", "fx", "fy", "ppx", "ppy", "depth_scale")


@dataclass(frozen=True)
class Frame:
    """One registered RGB-D frame.

    ``color``: (H, W, 3) uint8, **RGB** channel order. ``depth``: (H, W) uint16 in units of
    ``intrinsics.depth_scale`` metres, 0 where the camera has no reading; at least one reading
    is required. ``intrinsics.width`` = W and ``intrinsics.height`` = H.
    """

    color: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics

    def __post_init__(self) -> None:
        _check_frame(self.color, self.depth, self.intrinsics, "color", "depth", "intrinsics")

    @property
    def depth_mm(self) -> np.ndarray:
        """(H, W) float32 depth in millimetres, NaN where there is no reading."""
        depth = self.depth.astype(np.float32) * np.float32(self.intrinsics.depth_scale * 1000.0)
        depth[self.depth == 0] = np.nan
        return depth


def load_frame(path: str | os.PathLike[str]) -> Frame:
    """Read a frame folder (``color.png``, ``depth.png``, ``intrinsics.json``).

    Returns:
        ``Frame``: ``color`` uint8 (H, W, 3) RGB, ``depth`` uint16 (H, W) in units of
        ``intrinsics.depth_scale`` metres (0: no reading), ``intrinsics`` (px; metres per unit).

    Example:
        >>> from pathlib import Path
        >>> import vision
        >>> data = Path(vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> frame = load_frame(data / "circle_open")
        >>> frame.color.shape, frame.depth.dtype.name, frame.intrinsics.fx, frame.intrinsics.depth_scale
        ((480, 640, 3), 'uint16', 385.0, 0.0001)
    """
    folder = Path(path)
    if not folder.exists():
        raise FrameError(f"frame folder {folder} does not exist: give a folder written by "
                         f"'softgrip capture' (or one with {COLOR_FILE}, {DEPTH_FILE}, "
                         f"{INTRINSICS_FILE})")
    if not folder.is_dir():
        raise FrameError(f"{folder} is not a folder: a frame is a folder with {COLOR_FILE}, "
                         f"{DEPTH_FILE} and {INTRINSICS_FILE}")
    color_path, depth_path, intr_path = (folder / COLOR_FILE, folder / DEPTH_FILE,
                                         folder / INTRINSICS_FILE)
    color = _read_png(color_path)
    if color.ndim == 3 and color.shape[2] == 3:
        color = cv2.cvtColor(color, cv2.COLOR_BGR2RGB)
    depth = _read_png(depth_path)
    intrinsics = Intrinsics.from_dict(_read_json(intr_path), source=str(intr_path))
    _check_frame(color, depth, intrinsics, str(color_path), str(depth_path), str(intr_path))
    return Frame(color=color, depth=depth, intrinsics=intrinsics)


def save_frame(frame: Frame, path: str | os.PathLike[str]) -> Path:
    """Write ``frame`` as the folder ``path`` and return it; never overwrites anything.

    The files are written into a hidden temporary sibling folder that is renamed to ``path`` once
    complete, so ``path`` either does not exist or holds a whole frame. Missing parent folders are
    created.

    Example:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np
        >>> from vision.synthetic.render import d405_intrinsics
        >>> frame = Frame(np.zeros((480, 640, 3), np.uint8), np.full((480, 640), 1200, np.uint16), d405_intrinsics())
        >>> with tempfile.TemporaryDirectory() as root:
        ...     path = save_frame(frame, next_frame_dir(root))
        ...     print(path.name, int(load_frame(path).depth[0, 0]), next_frame_dir(root).name)
        frame_0000 1200 frame_0001
    """
    target = Path(path)
    _refuse_existing(target)
    color_png = _encode_png(cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), target / COLOR_FILE)
    depth_png = _encode_png(frame.depth, target / DEPTH_FILE)
    intr_json = (json.dumps(frame.intrinsics.to_dict(), indent=2) + "\n").encode()
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.partial"
    tmp.mkdir()  # not tempfile.mkdtemp: that makes the folder private (0700) instead of umask
    try:
        for name, data in ((COLOR_FILE, color_png), (DEPTH_FILE, depth_png),
                           (INTRINSICS_FILE, intr_json)):
            _write_file(tmp / name, data)
        _refuse_existing(target)
        os.rename(tmp, target)
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, OSError):
            raise FrameError(f"could not write frame {target}: {err}") from err
        raise
    return target


def next_frame_dir(root: str | os.PathLike[str], prefix: str = "frame") -> Path:
    """The first of ``root/<prefix>_0000``, ``root/<prefix>_0001``, ... that does not exist.

    Example:
        >>> next_frame_dir("/nonexistent/frames").name
        'frame_0000'
    """
    root = Path(root)
    index = 0
    while (root / f"{prefix}_{index:04d}").exists():
        index += 1
    return root / f"{prefix}_{index:04d}"


def _check_frame(color: Any, depth: Any, intrinsics: Any,
                 color_name: str, depth_name: str, intr_name: str) -> None:
    """Validate a colour/depth/intrinsics triple; messages use the given names (file paths)."""
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.ndim != 3 \
            or color.shape[2] != 3:
        raise FrameError(f"{color_name} must be an 8-bit colour image with 3 channels (RGB), got "
                         f"{_describe(color)}: convert it to 8-bit RGB")
    if isinstance(depth, np.ndarray) and depth.dtype == np.uint8:
        raise FrameError(f"{depth_name} is 8-bit: depth must be 16-bit (uint16) in units of "
                         f"depth_scale metres, 0 = no reading; save the camera's raw depth, not a "
                         f"visualisation")
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
        raise FrameError(f"{depth_name} must be a 16-bit single-channel depth image, got "
                         f"{_describe(depth)}")
    if color.shape[:2] != depth.shape:
        raise FrameError(f"{color_name} is {color.shape[1]}x{color.shape[0]} but {depth_name} is "
                         f"{depth.shape[1]}x{depth.shape[0]} (width x height): depth must be "
                         f"registered to the colour image, at the same size")
    if not isinstance(intrinsics, Intrinsics):
        raise FrameError(f"{intr_name} must be an Intrinsics, got {type(intrinsics).__name__}")
    if (intrinsics.width, intrinsics.height) != (depth.shape[1], depth.shape[0]):
        raise FrameError(f"{intr_name} says {intrinsics.width}x{intrinsics.height} but the images "
                         f"are {depth.shape[1]}x{depth.shape[0]}: use the intrinsics of the "
                         f"colour stream at this resolution")
    if not depth.any():
        raise FrameError(f"{depth_name} has no depth readings (every pixel is 0): check that the "
                         f"camera sees the scene within its depth range")


def _describe(array: Any) -> str:
    if not isinstance(array, np.ndarray):
        return type(array).__name__
    bits = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(array.dtype,
                                                                           str(array.dtype))
    channels = 1 if array.ndim == 2 else array.shape[-1] if array.ndim == 3 else None
    if channels is None:
        return f"{bits} array of shape {array.shape}"
    return f"{bits} with {channels} channel(s)"


#: Largest width or height of a frame image (px), checked in the PNG header before decoding, so that a
#: file claiming 60000x60000 px (or a small file that inflates to gigabytes) is refused at once.
MAX_IMAGE_SIDE = 8192


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's header (its IHDR chunk), or None if there is none."""
    if len(data) >= 24 and data.startswith(_PNG_SIGNATURE) and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def _read_png(path: Path) -> np.ndarray:
    data = _read_file(path)
    size = png_size(data)
    if size is not None and not all(1 <= side <= MAX_IMAGE_SIDE for side in size):
        raise FrameError(f"{path}: its header says {size[0]}x{size[1]} px; a frame image may be at most "
                         f"{MAX_IMAGE_SIDE} px wide and high (a RealSense gives up to 1920x1080): is it the "
                         f"right file, or damaged?")
    problem = _png_damage(data)
    image = None if problem else cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(f"{path} is not a readable PNG image ({problem or 'OpenCV cannot decode it'}): "
                         f"write it again, e.g. with 'softgrip capture'")
    return image


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_damage(data: bytes) -> str | None:
    """What is wrong with the PNG file structure of ``data`` (signature, chunk lengths and CRCs, the
    IEND chunk), or None. Checked before decoding, because libpng prints its own complaint about a
    damaged file on stderr before OpenCV gives up."""
    if not data:
        return "the file is empty"
    if not data.startswith(_PNG_SIGNATURE):
        return "no PNG signature"
    at = len(_PNG_SIGNATURE)
    while at + 12 <= len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        kind, end = data[at + 4:at + 8], at + 12 + length
        if end > len(data):
            break
        if zlib.crc32(data[at + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            return f"its {kind.decode('latin-1')!r} chunk at byte {at} is damaged (CRC mismatch)"
        if kind == b"IEND":
            return None
        at = end
    return f"truncated after {len(data)} bytes"


def _read_json(path: Path) -> Any:
    try:
        return user_json.loads(_read_file(path).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise FrameError(f"{path} is not valid JSON ({err}): it must be an object with keys "
                         f"{', '.join(_FIELDS)}") from None


#: Largest frame file read (bytes): a 1920x1080 16-bit PNG without compression is about 4 MB.
MAX_FILE_BYTES = 256 * 1024 * 1024


def _read_file(path: Path) -> bytes:
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise FrameError(f"{path} is not a regular file (a folder, FIFO or device): a frame folder needs the "
                             f"files {COLOR_FILE}, {DEPTH_FILE} and {INTRINSICS_FILE}")
        if st.st_size > MAX_FILE_BYTES:
            raise FrameError(f"{path} is {st.st_size / 2**20:.0f} MiB, more than a frame file can be "
                             f"({MAX_FILE_BYTES // 2**20} MiB): is it the right file?")
        return path.read_bytes()
    except FileNotFoundError:
        raise FrameError(f"{path} is missing: a frame folder needs {COLOR_FILE}, {DEPTH_FILE} and "
                         f"{INTRINSICS_FILE}") from None
    except OSError as err:
        raise FrameError(f"cannot read {path}: {err.strerror}") from None


def _encode_png(image: np.ndarray, name: Path) -> bytes:
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise FrameError(f"OpenCV could not encode {name} as PNG")
    return buffer.tobytes()


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "xb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _refuse_existing(path: Path) -> None:
    if os.path.lexists(path):
        raise FrameError(f"{path} already exists: captures are never overwritten; choose another "
                         f"folder or remove it first")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) \
        and not isinstance(value, (bool, np.bool_))
