"""Segmentation of an RGB-D frame into the two fingers and the object.

Every pixel is classified in two stages:

1. **Pixel classification and morphology** (the backend's part, batched for kornia):
   - *foreground* is every pixel nearer than the background cut-off (``background_depth_mm``,
     or automatic from the depth histogram: :func:`background_cutoff_mm`). A pixel without a depth reading
     (depth 0, a "hole") is foreground when a dilation of the foreground (``hole_fill_px``) covers
     it: holes inside and at the edges of the gripper and object (where stereo cameras lose depth)
     are filled, and their colour then decides what they are; holes far from the foreground stay
     background;
   - *gripper*: foreground that is light and unsaturated (HSV saturation at most
     ``gripper_max_saturation``, value at least ``gripper_min_value``; white or grey silicone);
   - *object*: foreground that is saturated (at least ``object_min_saturation``, value at least
     ``object_min_value``);
   - each is opened (``gripper_open_px``, ``object_open_px``) to remove specks. Only pixels inside
     ``roi`` count.
2. **Components** (OpenCV on the CPU for both backends): the fingers are the two largest gripper
   components (at least ``min_finger_px`` each), the left one being the one whose centroid is
   further left; with ``center_column`` set, the gripper mask is cut at that column instead and each
   finger is the largest component on its side (this separates fingers that touch each other).
   When only one component is big enough (fingertips touching, or the gripper's body joining the
   finger bases), that region is cut at a column: the caller's ``center_hint`` (where another frame
   of the same set-up put the centre line), else the region's **neck** (see :func:`neck_column`);
   a region without a clear neck (e.g. one finger in view) is an error, never a guessed split.
   Depth holes the object's mask encloses, beyond ``hole_fill_px``'s reach, are object where they
   have its colour (:func:`fill_enclosed_holes`). Object components smaller than ``min_object_px``
   are dropped. An empty object mask is not an error: the scene has no object (contact case (a));
   :func:`missing_object` says when the frame seems to show one the thresholds missed.

Saturation and value are fractions in [0, 1] for both backends: the OpenCV backend converts the
colour in float32 (``cv2.cvtColor``, hue in degrees, unused) and the kornia backend with
``kornia.color.rgb_to_hsv`` (hue in radians, unused), so the same thresholds mean the same thing.

Example:
    >>> from synthetic.render import Scene, render, d405_intrinsics
    >>> from synthetic.scenes import gripper_centrelines
    >>> frame = render(Scene(gripper_centrelines((0.0, -40.0), 50.0, 52.0)), d405_intrinsics())
    >>> seg = segment(frame)
    >>> bool(seg.left_finger.any() and seg.right_finger.any()), bool(seg.object.any())
    (True, False)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, NoReturn

import cv2
import numpy as np
from numpy.typing import ArrayLike

from softgrip_jax import SoftgripError
from softgrip_vision.frames import COLOR_FILE, Frame, greyscale_problem

Backend = Literal["opencv", "kornia"]
Split = Literal["components", "center_column", "center_hint", "neck", "none"]

#: A neck is at most this fraction of the smaller of the column counts (px per column) of the two
#: halves' peaks: the region is much thinner there than across either finger.
NECK_MAX_FRACTION = 0.5
#: Below the region's middle row, the region is at most this many finger widths tall at a neck
#: (a pinch where two fingertips touch, not the bottom of one curled finger).
NECK_MAX_PINCH = 0.75
#: Each side of a cut has at least this fraction of the other side's area (two fingers of one gripper).
CUT_MIN_BALANCE = 0.25


#: Largest side (px) of the dilation and opening kernels: a kernel is side x side bytes, and one
#: wider than a frame means nothing (the defaults are 15 and 3).
MAX_KERNEL_PX = 255


class SegmentationError(SoftgripError):
    """The frame cannot be segmented as a two-finger gripper; the message says what to adjust."""


@dataclass(frozen=True)
class SegmentationSettings:
    """Thresholds of :func:`segment` (all settable in the calibration profile).

    Attributes:
        background_depth_mm: pixels deeper than this (mm) are background; None picks it per frame
            from the depth histogram (see :func:`background_cutoff_mm`).
        gripper_max_saturation: largest HSV saturation (0-1) of a gripper pixel.
        gripper_min_value: smallest HSV value (brightness, 0-1) of a gripper pixel.
        object_min_saturation: smallest saturation (0-1) of an object pixel; must exceed
            ``gripper_max_saturation``.
        object_min_value: smallest value (0-1) of an object pixel (very dark pixels have
            meaningless saturation).
        hole_fill_px: side (px, odd, 0 = off) of the elliptic dilation of the foreground that
            decides which depth holes are filled: hole pixels within about half of it from a
            foreground reading are foreground (their colour then classifies them).
        gripper_open_px: side (px, odd, 0 = off) of the elliptic opening of the gripper mask
            (removes specks and ragged edges).
        object_open_px: the same for the object mask; off by default because an opening rounds
            corners sharper than its size, and the object's corners are where contact is decided.
        min_finger_px: smallest gripper component (px) counted as a finger.
        min_object_px: object components smaller than this (px) are dropped.
        center_column: image column (px) between the fingers, or None to take the midpoint of the
            two largest gripper components' centroids.
        roi: region of interest ``(x0, y0, x1, y1)`` in px (columns x0..x1-1, rows y0..y1-1), or
            None for the whole frame. Use it to leave out the gripper's body above the fingers.
    """

    background_depth_mm: float | None = None
    gripper_max_saturation: float = 0.25
    gripper_min_value: float = 0.55
    object_min_saturation: float = 0.35
    object_min_value: float = 0.15
    hole_fill_px: int = 15
    gripper_open_px: int = 3
    object_open_px: int = 0
    min_finger_px: int = 200
    min_object_px: int = 30
    center_column: float | None = None
    roi: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        if self.background_depth_mm is not None:
            _check_real("background_depth_mm", self.background_depth_mm, lower=0.0, strict=True,
                        unit="mm (or None for automatic)")
        for name in ("gripper_max_saturation", "gripper_min_value", "object_min_saturation",
                     "object_min_value"):
            _check_real(name, getattr(self, name), lower=0.0, upper=1.0, unit="(a fraction 0-1)")
        if self.gripper_max_saturation >= self.object_min_saturation:
            raise SegmentationError(
                f"SegmentationSettings: gripper_max_saturation ({self.gripper_max_saturation}) must be "
                f"below object_min_saturation ({self.object_min_saturation}), or a pixel could be both")
        for name in ("hole_fill_px", "gripper_open_px", "object_open_px"):
            value = getattr(self, name)
            if not _is_int(value) or value < 0 or (value != 0 and value % 2 == 0) or value > MAX_KERNEL_PX:
                raise SegmentationError(f"SegmentationSettings.{name} must be 0 (off) or an odd number "
                                        f"of pixels up to {MAX_KERNEL_PX}, got {value!r}")
        for name in ("min_finger_px", "min_object_px"):
            value = getattr(self, name)
            if not _is_int(value) or value < 1:
                raise SegmentationError(f"SegmentationSettings.{name} must be an integer >= 1 (pixels), "
                                        f"got {value!r}")
        if self.center_column is not None:
            _check_real("center_column", self.center_column, lower=0.0, unit="px (or None)")
        if self.roi is not None:
            roi = self.roi
            if (not isinstance(roi, (tuple, list)) or len(roi) != 4 or not all(map(_is_int, roi))
                    or roi[0] < 0 or roi[1] < 0 or roi[0] >= roi[2] or roi[1] >= roi[3]):
                raise SegmentationError(f"SegmentationSettings.roi must be (x0, y0, x1, y1) integer "
                                        f"pixels with 0 <= x0 < x1 and 0 <= y0 < y1, got {roi!r}")
            object.__setattr__(self, "roi", tuple(int(c) for c in roi))

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict of every field (``roi`` as a list or None)."""
        d = dataclasses.asdict(self)
        d["roi"] = None if self.roi is None else list(self.roi)
        return d

    @classmethod
    def from_dict(cls, d: Any, source: str = "segmentation settings") -> SegmentationSettings:
        """Build from a JSON object; missing keys take their defaults, unknown keys are refused.

        Errors name ``source`` (e.g. the profile file) and the field.
        """
        if not isinstance(d, dict):
            raise SegmentationError(f"{source}: expected a JSON object of segmentation settings, "
                                    f"got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise SegmentationError(f"{source}: unknown segmentation setting(s) {', '.join(unknown)}; "
                                    f"valid ones: {', '.join(sorted(known))}")
        values = dict(d)
        if isinstance(values.get("roi"), list):
            values["roi"] = tuple(values["roi"])
        try:
            return cls(**values)
        except SegmentationError as err:
            raise SegmentationError(f"{source}: {err}") from None


@dataclass(frozen=True, eq=False)
class Segmentation:
    """The parts of one frame, each a bool (H, W) mask.

    Attributes:
        gripper: every gripper pixel (light, unsaturated foreground), fingers included.
        left_finger, right_finger: the two finger components (disjoint subsets of ``gripper``).
        object: the object's pixels; all False when there is no object.
        background_cutoff_mm: the depth cut-off used (mm); inf when no background was found.
        center_column: the column (px) separating the fingers: the midpoint of the two fingers'
            centroids (split ``"components"``), else the column the gripper region was cut at
            (pixel columns ``u < center_column`` went left).
        split: how the fingers were separated: ``"components"`` (two separate gripper regions),
            ``"center_column"`` (cut at ``SegmentationSettings.center_column``), ``"center_hint"``
            (one region, cut at the caller's ``center_hint``) or ``"neck"`` (one region, cut at its
            neck found in this frame, :func:`neck_column`). For every split but ``"components"``
            the two masks may meet along ``center_column``, which is then not a finger outline.
            ``"none"``: a frame of the object alone (:func:`segment_object`), both finger masks
            empty and ``center_column`` NaN.
    """

    gripper: np.ndarray
    left_finger: np.ndarray
    right_finger: np.ndarray
    object: np.ndarray
    background_cutoff_mm: float
    center_column: float
    split: Split = "components"

    @property
    def fingers(self) -> np.ndarray:
        """bool (H, W): both fingers, the pixels on the gripper plane."""
        return self.left_finger | self.right_finger


def segment(frame: Frame, settings: SegmentationSettings | None = None, *,
            center_hint: float | None = None) -> Segmentation:
    """Segment one frame with the OpenCV backend (see the module docstring).

    Args:
        frame: the RGB-D frame.
        settings: thresholds (defaults if None).
        center_hint: image column (px) of the gripper's centre line found in another frame of the
            same set-up (e.g. the open frame's ``center_column``), used to cut the gripper region
            when the fingers form one region; None to find the cut (the neck) in this frame.
            ``settings.center_column``, when set, takes precedence. The hint is used where its
            column could join two fingers (a pinch, or the body in the region's upper half, as at
            a neck: :func:`neck_column`); where it would cut through a finger (e.g. the tips of
            fingers of unequal Theta meet off the centre line) the region's neck is used instead
            (split ``"neck"``). Either cut must leave two sides of at least ``min_finger_px`` px
            and 1/4 of each other's area, else the frame is refused.

    Raises:
        SegmentationError: a greyscale colour image, no gripper, only one finger, no depth in the
            gripper region, or a region of interest outside the frame; the message names the setting
            to adjust.

    Example (masks are bool (H, W); the cut-off is in mm):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from softgrip_vision.frames import load_frame
        >>> seg = segment(load_frame(data / "circle_open"))
        >>> seg.object.shape, bool(seg.object.any()), bool((seg.left_finger & seg.right_finger).any())
        ((480, 640), True, False)
    """
    return segment_batch([frame], settings, center_hints=[center_hint])[0]


def segment_object(frame: Frame, settings: SegmentationSettings | None = None) -> Segmentation:
    """Segment a frame taken before the gripper is in view: the object only (stage 1 and the
    object's cleaning, as :func:`segment`; no finger is looked for).

    The finger masks are empty and ``split`` is ``"none"``; ``gripper`` holds whatever light,
    unsaturated foreground the frame shows (e.g. part of the approaching gripper), which is not the
    object. An empty object mask is not an error (no object: contact case (a)).

    Raises:
        SegmentationError: a greyscale colour image or a region of interest outside the frame.

    Example (a rendered disc, no gripper in view):
        >>> from synthetic.render import Scene, render, d405_intrinsics
        >>> angles = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
        >>> disc = np.stack([12.0 * np.cos(angles), 30.0 + 12.0 * np.sin(angles)], axis=-1)  # mm
        >>> seg = segment_object(render(Scene([], object_polygon=disc), d405_intrinsics()))
        >>> bool(seg.object.any()), bool(seg.fingers.any()), seg.split
        (True, False, 'none')
    """
    settings = SegmentationSettings() if settings is None else settings
    grey = greyscale_problem(frame.color)
    if grey is not None:
        raise SegmentationError(f"{COLOR_FILE} {grey}")
    cutoff = background_cutoff_mm(frame, settings)
    roi = _roi_mask(frame.depth.shape, settings.roi)
    gripper, obj = _classify_opencv(frame, settings, cutoff, roi)
    none = np.zeros_like(gripper)
    return Segmentation(gripper=gripper, left_finger=none, right_finger=none.copy(),
                        object=_drop_small(fill_enclosed_holes(obj, frame, settings), settings.min_object_px),
                        background_cutoff_mm=cutoff,
                        center_column=float("nan"), split="none")


def segment_batch(
    frames: Sequence[Frame],
    settings: SegmentationSettings | None = None,
    backend: Backend = "opencv",
    device: str = "cpu",
    *,
    center_hints: Sequence[float | None] | None = None,
) -> list[Segmentation]:
    """Segment several frames.

    Args:
        frames: the frames; for ``backend="kornia"`` all of one size.
        settings: thresholds (defaults if None).
        backend: ``"opencv"`` (default, frame by frame) or ``"kornia"`` (stage 1 batched on torch
            tensors on ``device``, meant for a GPU: on a CPU it is 20-40x slower than OpenCV, see
            benchmarks/vision_accuracy.py).
        device: torch device of the kornia backend, e.g. ``"cpu"`` or ``"cuda"``.
        center_hints: one centre-line column (px) or None per frame (see :func:`segment`), or None
            for no hints.

    Returns:
        One :class:`Segmentation` per frame, in order.

    Raises:
        SegmentationError: as :func:`segment`, naming the frame's index; also a bad backend,
            frames of different sizes for kornia, kornia not installed, or ``center_hints`` not
            one finite column (or None) per frame.

    Example:
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> segs = segment_batch([load_frame(data / name) for name in ("circle_open", "calib_open")])
        >>> [bool(s.object.any()) for s in segs]
        [True, False]
    """
    settings = SegmentationSettings() if settings is None else settings
    frames = list(frames)
    hints = _check_hints(center_hints, len(frames))
    for index, frame in enumerate(frames):  # no saturation: the object could not be told from the gripper
        grey = greyscale_problem(frame.color)
        if grey is not None:
            raise SegmentationError(("" if len(frames) == 1 else f"frame {index}: ") + f"{COLOR_FILE} {grey}")
    cutoffs = [background_cutoff_mm(frame, settings) for frame in frames]
    rois = [_roi_mask(frame.depth.shape, settings.roi) for frame in frames]
    if backend == "opencv":
        raw = [_classify_opencv(f, settings, c, r) for f, c, r in zip(frames, cutoffs, rois)]
    elif backend == "kornia":
        raw = _classify_kornia(frames, settings, cutoffs, rois, device) if frames else []
    else:
        raise SegmentationError(f"unknown segmentation backend {backend!r}: use 'opencv' or 'kornia'")
    results = []
    for index, (frame, cutoff, roi, (gripper, obj), hint) in enumerate(zip(frames, cutoffs, rois, raw, hints)):
        try:
            results.append(_components(frame, settings, cutoff, roi, gripper, obj, hint))
        except SegmentationError as err:
            if len(frames) == 1:
                raise
            raise SegmentationError(f"frame {index}: {err}") from None
    return results


def background_cutoff_mm(frame: Frame, settings: SegmentationSettings) -> float:
    """The depth (mm) beyond which ``frame``'s pixels are background.

    ``settings.background_depth_mm`` if set. Otherwise the depth readings in the region of interest
    are split in a near and a far class by Otsu's method, and the cut-off is the middle of the gap
    between them (halfway from the near class's 99th percentile to the far class's 1st), so depth
    noise on either side stays on its side. inf (no background in view) when the far class's mean
    is less than 25 % deeper than the near class's.

    Example (the samples: gripper and object at 120-123 mm, background at 400 mm):
        >>> from pathlib import Path
        >>> import softgrip_vision
        >>> data = Path(softgrip_vision.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> from softgrip_vision.frames import load_frame
        >>> 123 < background_cutoff_mm(load_frame(data / "circle_open"), SegmentationSettings()) < 400
        True
    """
    if settings.background_depth_mm is not None:
        return float(settings.background_depth_mm)
    mm_per_unit = frame.intrinsics.depth_scale * 1000.0
    readings = frame.depth[_roi_mask(frame.depth.shape, settings.roi)]
    readings = readings[readings > 0]
    if readings.size == 0:
        return math.inf
    threshold, _ = cv2.threshold(readings.reshape(-1, 1), 0, 65535, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    near, far = readings[readings <= threshold], readings[readings > threshold]
    if near.size == 0 or far.size == 0 or far.mean() < 1.25 * near.mean():  # one depth: no split
        return math.inf
    return 0.5 * float(np.percentile(near, 99) + np.percentile(far, 1)) * mm_per_unit


def _classify_opencv(frame: Frame, settings: SegmentationSettings, cutoff_mm: float,
                     roi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stage 1 with OpenCV: (gripper, object) bool (H, W) masks before components."""
    saturation, value = _saturation_value(frame)
    depth_mm = frame.depth.astype(np.float32) * np.float32(frame.intrinsics.depth_scale * 1000.0)
    valid = frame.depth > 0
    near = valid & (depth_mm <= np.float32(cutoff_mm))
    if settings.hole_fill_px:
        grown = cv2.dilate(near.view(np.uint8), _kernel(settings.hole_fill_px))
        near |= ~valid & grown.view(bool)
    foreground = near & roi
    gripper = foreground & (saturation <= np.float32(settings.gripper_max_saturation)) \
        & (value >= np.float32(settings.gripper_min_value))
    obj = foreground & _object_coloured(saturation, value, settings)
    if settings.gripper_open_px:
        gripper = cv2.morphologyEx(gripper.view(np.uint8), cv2.MORPH_OPEN, _kernel(settings.gripper_open_px))
    if settings.object_open_px:
        obj = cv2.morphologyEx(obj.view(np.uint8), cv2.MORPH_OPEN, _kernel(settings.object_open_px))
    return gripper.view(bool), obj.view(bool)


def _classify_kornia(frames: list[Frame], settings: SegmentationSettings, cutoffs: list[float],
                     rois: list[np.ndarray], device: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Stage 1 with kornia, all frames in one batch of torch tensors on ``device``."""
    try:
        import kornia
        import torch
    except ImportError as err:
        raise SegmentationError(f"backend='kornia' needs torch and kornia ({err}): install them "
                                f"with pip install 'softgrip-jax[kornia]', or use backend='opencv'") from None
    sizes = {frame.depth.shape for frame in frames}
    if len(sizes) > 1:
        raise SegmentationError(f"backend='kornia' segments one batch, so all frames must have one size; "
                                f"got sizes (height, width) {sorted(sizes)}: segment them in groups")

    def tensor(arrays: Sequence[ArrayLike]) -> Any:
        return torch.from_numpy(np.stack(arrays)).to(device)

    color = tensor([frame.color for frame in frames]).permute(0, 3, 1, 2).float() / 255.0
    hsv = kornia.color.rgb_to_hsv(color)  # (B, 3, H, W): hue in radians (unused), S and V in [0, 1]
    saturation, value = hsv[:, 1:2], hsv[:, 2:3]
    depth = tensor([frame.depth.astype(np.int32) for frame in frames])[:, None].float()
    mm_per_unit = tensor([np.float32(f.intrinsics.depth_scale * 1000.0) for f in frames]).view(-1, 1, 1, 1)
    cutoff = tensor([np.float32(c) for c in cutoffs]).view(-1, 1, 1, 1)
    valid = depth > 0
    near = valid & (depth * mm_per_unit <= cutoff)
    if settings.hole_fill_px:
        grown = kornia.morphology.dilation(near.float(), _kernel_tensor(settings.hole_fill_px, device)) > 0.5
        near = near | (~valid & grown)
    foreground = near & tensor(rois)[:, None]
    gripper = foreground & (saturation <= settings.gripper_max_saturation) \
        & (value >= settings.gripper_min_value)
    obj = foreground & (saturation >= settings.object_min_saturation) & (value >= settings.object_min_value)
    if settings.gripper_open_px:
        gripper = kornia.morphology.opening(gripper.float(), _kernel_tensor(settings.gripper_open_px, device)) > 0.5
    if settings.object_open_px:
        obj = kornia.morphology.opening(obj.float(), _kernel_tensor(settings.object_open_px, device)) > 0.5
    gripper, obj = gripper[:, 0].cpu().numpy(), obj[:, 0].cpu().numpy()
    return list(zip(gripper, obj))


def _object_coloured(saturation: np.ndarray, value: np.ndarray, settings: SegmentationSettings) -> np.ndarray:
    """bool (H, W): pixels of an object's colour (saturation and value at least the object's thresholds)."""
    return (saturation >= np.float32(settings.object_min_saturation)) & (value >= np.float32(settings.object_min_value))


def _saturation_value(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """HSV saturation and value (H, W) float32 in [0, 1] of the frame's colour, by OpenCV."""
    hsv = cv2.cvtColor(frame.color.astype(np.float32) * np.float32(1 / 255), cv2.COLOR_RGB2HSV)
    return hsv[..., 1], hsv[..., 2]


def _kernel(size: int) -> np.ndarray:
    """uint8 (size, size) elliptic structuring element, the same for both backends."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


def _kernel_tensor(size: int, device: str) -> Any:
    import torch

    return torch.from_numpy(_kernel(size).astype(np.float32)).to(device)


def _roi_mask(shape: tuple[int, int], roi: tuple[int, int, int, int] | None) -> np.ndarray:
    """bool (H, W): True inside the region of interest (everywhere if None)."""
    inside = np.zeros(shape, dtype=bool)
    if roi is None:
        inside[:] = True
        return inside
    x0, y0, x1, y1 = roi
    if x0 >= shape[1] or y0 >= shape[0]:
        raise SegmentationError(f"SegmentationSettings.roi {roi} starts outside the {shape[1]}x{shape[0]} "
                                f"frame: give (x0, y0, x1, y1) in pixels of this frame")
    inside[y0:y1, x0:x1] = True
    return inside


def _check_hints(center_hints: Sequence[float | None] | None, n_frames: int) -> list[float | None]:
    """The centre-line hints as one float (px) or None per frame."""
    if center_hints is None:
        return [None] * n_frames
    hints = list(center_hints)
    if len(hints) != n_frames:
        raise SegmentationError(f"center_hints must give one column (or None) per frame: got {len(hints)} "
                                f"for {n_frames} frame(s)")
    for index, hint in enumerate(hints):
        if hint is not None and not (_is_real(hint) and math.isfinite(hint)):
            raise SegmentationError(f"center_hints[{index}] must be a finite image column (px) or None, "
                                    f"got {hint!r}")
    return [None if hint is None else float(hint) for hint in hints]


def _components(frame: Frame, settings: SegmentationSettings, cutoff_mm: float, roi: np.ndarray,
                gripper: np.ndarray, obj: np.ndarray, center_hint: float | None = None) -> Segmentation:
    """Stage 2: split the gripper into fingers and clean the object mask."""
    width = gripper.shape[1]
    split: Split
    if settings.center_column is not None:
        center = float(settings.center_column)
        if center >= width:
            raise SegmentationError(f"SegmentationSettings.center_column={center:g} is outside the frame "
                                    f"(width {width} px): give a column between the fingers, or None")
        left_side = np.arange(width) < center
        left = _largest_component(gripper & left_side, settings.min_finger_px)
        right = _largest_component(gripper & ~left_side, settings.min_finger_px)
        if left is None and right is None:
            _raise_no_gripper(frame, settings, cutoff_mm, roi)
        if left is None or right is None:
            side = "left" if left is None else "right"
            raise SegmentationError(
                f"only one finger found: no gripper region of at least min_finger_px="
                f"{settings.min_finger_px} px {side} of center_column={center:g}; expected one finger "
                f"on each side: check that both fingers are in view, or move center_column between them")
        split = "center_column"
    else:
        _, labels, stats, centroids = cv2.connectedComponentsWithStats(gripper.view(np.uint8), connectivity=8)
        order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")
        big = [k for k in order if stats[k, cv2.CC_STAT_AREA] >= settings.min_finger_px]
        if not big:
            _raise_no_gripper(frame, settings, cutoff_mm, roi)
        if len(big) >= 2:
            first, second = sorted(big[:2], key=lambda k: centroids[k, 0])
            left, right = labels == first, labels == second
            center = 0.5 * float(centroids[first, 0] + centroids[second, 0])
            split = "components"
        else:
            k = big[0]
            region = labels == k
            where = f"{stats[k, cv2.CC_STAT_AREA]} px around column {centroids[k, 0]:.0f}"
            hint_cuts = center_hint is not None and 0.0 <= center_hint < width \
                and _neck_is_a_junction(region, center_hint)
            if center_hint is not None and hint_cuts:
                center, split = center_hint, "center_hint"
                source = f"center_hint={center_hint:g} (the centre line of another frame)"
            else:  # no hint, or one that would cut through a finger (e.g. fingers of unequal Theta)
                neck = neck_column(region)
                if neck is None:
                    from softgrip_vision.plausibility import UPSIDE_DOWN_FIX, body_below_fingers

                    if body_below_fingers(region):
                        raise SegmentationError(
                            f"the frame looks upside down: the gripper's body joins the fingers below them "
                            f"({where}), where it joins their bases above them; {UPSIDE_DOWN_FIX}")
                    hint_note = "" if center_hint is None else (
                        f", and center_hint={center_hint:g} does not cut it where two fingers could meet")
                    raise SegmentationError(
                        f"only one finger found ({where}, no neck where two fingers would meet{hint_note}); "
                        f"expected two separate finger regions of at least min_finger_px="
                        f"{settings.min_finger_px} px: check that both fingers are in view; if they touch "
                        f"each other or the gripper's body joins them, set center_column to a column "
                        f"between them or roi to leave the body out")
                center, split = neck, "neck"
                source = f"its neck at column {neck:.1f}"
            left, right = _cut_region(region, center, settings.min_finger_px, where, source)
    return Segmentation(
        gripper=gripper,
        left_finger=left,
        right_finger=right,
        object=_drop_small(fill_enclosed_holes(obj, frame, settings), settings.min_object_px),
        background_cutoff_mm=cutoff_mm,
        center_column=center,
        split=split,
    )


def neck_column(region: np.ndarray) -> float | None:
    """The column (px) where one region made of two fingers is thinnest between them, or None.

    The region's column counts ``n(u)`` (pixels per column) are split at its centroid column; the
    highest column of each half is that half's peak (across a finger's straight stretch near its
    base). The neck is the thinnest column between the two peaks: the columns within
    ``max(1, n_min / 10)`` px of the smallest count ``n_min`` there form runs, and the neck is the
    middle of the longest run (of the one nearest the centroid among equally long ones), e.g. the
    middle of the point where two fingertips touch, or of the gap between two fingers joined by the
    gripper's body. There is no clear neck (None) when ``n_min`` exceeds ``NECK_MAX_FRACTION`` (1/2)
    of the smaller peak: a single finger's column counts fall off toward its tip without rising
    again; nor when the region is at least ``NECK_MAX_PINCH`` (3/4) of a finger's width (twice the
    median over rows of the largest distance-transform value) tall in the neck's column in a run
    reaching below the region's middle row: that is one finger curled into a U, not two fingertips
    touching (a pinch) or the gripper's body joining the bases (wholly above the middle).
    :func:`segment` further requires each side of the cut to hold at least ``min_finger_px`` px and
    at least ``CUT_MIN_BALANCE`` (1/4) of the other side's area.

    Args:
        region: bool (H, W), one connected region.

    Returns:
        The neck's column u (px, pixel centres at integers; a half-integer between two columns),
        or None.

    Example (two 6-px-wide blocks joined by a 1-px bridge across columns 8-11):
        >>> m = np.zeros((10, 20), bool)
        >>> m[:, 2:8] = m[:, 12:18] = True
        >>> m[4, 8:12] = True
        >>> neck_column(m), neck_column(m[:, :8])
        (9.5, None)
    """
    counts = region.sum(axis=0).astype(np.float64)
    columns = np.nonzero(counts)[0]
    if columns.size < 3:
        return None
    u = np.arange(counts.size, dtype=np.float64)
    centroid = float((counts * u).sum() / counts.sum())
    halves = u < centroid
    if not halves.any() or halves.all():
        return None
    first = int(np.argmax(np.where(halves, counts, -1.0)))
    second = int(np.argmax(np.where(halves, -1.0, counts)))
    between = counts[first:second + 1]
    smallest = float(between.min())
    if second - first < 2 or smallest > NECK_MAX_FRACTION * min(counts[first], counts[second]):
        return None
    near = np.concatenate([[False], between <= smallest + max(1.0, 0.1 * smallest), [False]])
    edges = np.flatnonzero(np.diff(near.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2] - 1  # inclusive runs, indices into ``between``
    middles = first + 0.5 * (starts + stops)
    best = min(range(len(starts)), key=lambda i: (-(stops[i] - starts[i]), abs(middles[i] - centroid)))
    neck = float(middles[best])
    return neck if _neck_is_a_junction(region, neck) else None


def _neck_is_a_junction(region: np.ndarray, neck: float) -> bool:
    """Whether the region's pixels in column ``neck`` (px; both columns next to a half-integer)
    could join two fingers: each vertical run of them is a pinch (shorter than ``NECK_MAX_PINCH``
    finger widths: fingertips touching) or lies wholly in the upper half of the region (the
    gripper's body above the bases). A run as thick as a finger low in the region is the bottom of one finger
    curled into a U (or a cut through a finger)."""
    last = region.shape[1] - 1
    column = region[:, min(int(math.floor(neck)), last)] | region[:, min(int(math.ceil(neck)), last)]
    distance = cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    rows = np.flatnonzero(region.any(axis=1))
    width = 2.0 * float(np.median(distance[rows].max(axis=1)))  # a finger's width (px)
    middle = 0.5 * (rows[0] + rows[-1])
    edges = np.flatnonzero(np.diff(np.concatenate([[0], column.view(np.int8), [0]])))
    for start, stop in zip(edges[0::2], edges[1::2]):  # rows start..stop-1
        if stop - start >= NECK_MAX_PINCH * width and stop - 1 > middle:
            return False
    return True


def _cut_region(region: np.ndarray, center: float, min_px: int, where: str,
                source: str) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) bool (H, W): the largest component of ``region`` on each side of column
    ``center`` (columns u < center go left); each must hold at least ``min_px`` px and at least
    ``CUT_MIN_BALANCE`` of the other's area, or the cut does not separate two fingers."""
    left_side = np.arange(region.shape[1]) < center
    left = _largest_component(region & left_side, 1)
    right = _largest_component(region & ~left_side, 1)
    areas = [0 if m is None else int(m.sum()) for m in (left, right)]
    if left is None or right is None or min(areas) < min_px or min(areas) < CUT_MIN_BALANCE * max(areas):
        raise SegmentationError(
            f"only one finger found: the one gripper region ({where}) cut at {source} leaves "
            f"{areas[0]} px on the left and {areas[1]} px on the right; expected a finger of at least "
            f"min_finger_px={min_px} px on each side, neither under {CUT_MIN_BALANCE:g} of the other: check "
            f"that both fingers are in view; if they touch each other or the gripper's body joins them, "
            f"set center_column to a column between them or roi to leave the body out")
    return left, right


def fill_enclosed_holes(obj: np.ndarray, frame: Frame, settings: SegmentationSettings) -> np.ndarray:
    """bool (H, W): ``obj`` with the depth holes it encloses filled where they have the object's colour.

    Stage 1 fills a hole (no depth reading) only within about ``hole_fill_px / 2`` of a reading, so
    a larger hole inside the object (a shiny patch, a stereo dropout on a plain face) would punch a
    free-space pocket into it. Pixels the object mask encloses (not reachable from the image's
    border without crossing the mask) that have no reading and the object's colour (saturation and
    value at least ``object_min_saturation``, ``object_min_value``) are object. Enclosed pixels that
    have a reading (background seen through a ring) or another colour stay out.

    Example (a ring of object pixels around a hole without depth, of the object's red):
        >>> from softgrip_vision.frames import Frame, Intrinsics
        >>> obj = np.zeros((9, 9), bool); obj[2:7, 2:7] = True; obj[3:6, 3:6] = False
        >>> color = np.zeros((9, 9, 3), np.uint8); color[..., 0] = 200          # red everywhere
        >>> depth = np.full((9, 9), 500, np.uint16); depth[3:6, 3:6] = 0          # no reading inside
        >>> frame = Frame(color=color, depth=depth, intrinsics=Intrinsics(9, 9, 10.0, 10.0, 4.0, 4.0, 0.001))
        >>> int(fill_enclosed_holes(obj, frame, SegmentationSettings()).sum()), int(obj.sum())
        (25, 16)
    """
    walls = np.zeros((obj.shape[0] + 2, obj.shape[1] + 2), np.uint8)  # a free border all round
    walls[1:-1, 1:-1] = obj
    cv2.floodFill(walls, None, (0, 0), 2)  # the 4-connected free space reachable from outside
    holes = (walls[1:-1, 1:-1] == 0) & (frame.depth == 0)
    if not holes.any():
        return obj
    return obj | (holes & _object_coloured(*_saturation_value(frame), settings))


#: Widest band (px) of mixed edge pixels along an outline that :func:`missing_object` ignores.
_EDGE_BAND_PX = 7


def missing_object(frame: Frame, settings: SegmentationSettings, seg: Segmentation) -> str | None:
    """Why ``frame`` seems to show an object although ``seg.object`` is empty, or None.

    Two things a camera shows that the thresholds miss: a region of at least ``min_object_px`` in
    front of the background (a finite ``seg.background_cutoff_mm``) that is neither object- nor
    gripper-coloured (too dark, or washed out by flat light; bands narrower than
    :data:`_EDGE_BAND_PX` along outlines, mixed edge pixels, do not count), and an object-coloured
    region of that size without depth readings (a surface the camera cannot measure). The text names
    the region, its colour and the settings to change.
    """
    roi = _roi_mask(frame.depth.shape, settings.roi)
    saturation, value = _saturation_value(frame)
    coloured = roi & _object_coloured(saturation, value, settings)

    def where(region: np.ndarray) -> str:
        v, u = np.nonzero(region)
        return f"{int(region.sum())} px around pixel ({u.mean():.0f}, {v.mean():.0f})"

    thresholds = (f"object_min_saturation={settings.object_min_saturation}, object_min_value="
                  f"{settings.object_min_value}")
    if math.isfinite(seg.background_cutoff_mm):
        depth_mm = frame.depth.astype(np.float32) * np.float32(frame.intrinsics.depth_scale * 1000.0)
        near = roi & (frame.depth > 0) & (depth_mm <= np.float32(seg.background_cutoff_mm))
        # Without the bands along every outline: edge pixels of mixed colour and depth ("flying
        # pixels" of a stereo camera) around a gripper in view are neither colour, and not an object.
        other = near & ~coloured & ~seg.gripper
        core = _largest_component(cv2.morphologyEx(other.view(np.uint8), cv2.MORPH_OPEN,
                                                   _kernel(_EDGE_BAND_PX)).view(bool), settings.min_object_px)
        if core is not None:  # reported: the whole region around that core, its specks and rim included
            _, labels = cv2.connectedComponents(other.view(np.uint8), connectivity=8)
            unclassified = np.isin(labels, np.unique(labels[core]))
            return (f"no object found, but a region of {where(unclassified)} stands in front of the background "
                    f"(cut-off {seg.background_cutoff_mm:.0f} mm) and is neither object- nor gripper-coloured "
                    f"(median saturation {float(np.median(saturation[unclassified])):.2f}, value "
                    f"{float(np.median(value[unclassified])):.2f}; an object needs {thresholds}): if it is the "
                    f"object, light it more evenly or lower those thresholds in the profile's segmentation settings")
    unmeasured = _largest_component(coloured & (frame.depth == 0), settings.min_object_px)
    if unmeasured is not None:
        return (f"no object found, but an object-coloured region of {where(unmeasured)} has no depth readings, so "
                f"it is not taken for the object: if it is the object, the camera cannot measure it (check its "
                f"depth range and that the surface is not too shiny or dark, and that depth is aligned to colour)")
    return None


def _largest_component(mask: np.ndarray, min_px: int) -> np.ndarray | None:
    """bool (H, W): the largest 8-connected component of ``mask`` if it has >= min_px pixels."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    if count < 2:
        return None
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k if stats[k, cv2.CC_STAT_AREA] >= min_px else None


def _drop_small(mask: np.ndarray, min_px: int) -> np.ndarray:
    """bool (H, W): ``mask`` without its 8-connected components smaller than min_px pixels."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False
    return keep[labels]


def _raise_no_gripper(frame: Frame, settings: SegmentationSettings, cutoff_mm: float,
                      roi: np.ndarray) -> NoReturn:
    """Explain why no finger was found: no depth there, too deep, or nothing gripper-coloured."""
    saturation, value = _saturation_value(frame)
    coloured = roi & (saturation <= np.float32(settings.gripper_max_saturation)) \
        & (value >= np.float32(settings.gripper_min_value))
    candidate = _largest_component(coloured, settings.min_finger_px)
    if candidate is not None:
        readings = frame.depth[candidate]
        readings = readings[readings > 0]
        if readings.size < 0.05 * candidate.sum():
            raise SegmentationError(
                f"no depth in the gripper region: a gripper-coloured region of {int(candidate.sum())} px "
                f"has depth readings on {readings.size} px only; the camera cannot measure the gripper: "
                f"check that it is within the camera's depth range and not too shiny, and that depth is "
                f"aligned to colour")
        depth_mm = float(np.median(readings)) * frame.intrinsics.depth_scale * 1000.0
        if depth_mm > cutoff_mm:
            raise SegmentationError(
                f"no gripper found in front of the background: the gripper-coloured region is at about "
                f"{depth_mm:.0f} mm, beyond the background cut-off of {cutoff_mm:.0f} mm; set "
                f"background_depth_mm above {depth_mm:.0f}")
    raise SegmentationError(
        f"no gripper found: expected two light, unsaturated regions (saturation <= "
        f"gripper_max_saturation={settings.gripper_max_saturation}, value >= gripper_min_value="
        f"{settings.gripper_min_value}) of at least min_finger_px={settings.min_finger_px} px in front "
        f"of the background (cut-off {cutoff_mm:.0f} mm); check that the gripper is in view and lit "
        f"evenly, or adjust gripper_max_saturation / gripper_min_value")


def _check_real(name: str, value: Any, *, lower: float, upper: float | None = None,
                strict: bool = False, unit: str = "") -> None:
    ok = _is_real(value) and math.isfinite(value) and (value > lower if strict else value >= lower) \
        and (upper is None or value <= upper)
    if not ok:
        bound = f"> {lower:g}" if strict else f">= {lower:g}"
        if upper is not None:
            bound = f"in [{lower:g}, {upper:g}]"
        raise SegmentationError(f"SegmentationSettings.{name} must be a finite number {bound} {unit}, "
                                f"got {value!r}".rstrip())


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
