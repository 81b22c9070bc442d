"""A scene from a frame of the object alone, the gripper placed by the arm.

A planner often sees the object before the gripper is in view. Then nothing in the frame says
where the gripper plane is; the arm does: its forward kinematics (with the camera's hand-eye
calibration) give the gripper's pose in camera coordinates, a 4 x 4 transform ``T`` (mm) taking
points of the gripper's frame to the camera's. The gripper's frame:

* origin: the point midway between the two finger bases, on the fingers' centrelines;
* x axis: from the left finger's base toward the right finger's base;
* y axis: along the open fingers, from their bases toward their tips;
* z axis: x cross y, the gripper plane's normal, pointing away from the camera.

The camera's frame is the optical one of OpenCV and pyrealsense2 (x right, y down, z forward), in
mm. The gripper plane is then the gripper frame's x-y plane, and the pose (x mm, y mm, angle rad)
of :class:`~softgrip_vision.scene.Scene` follows from ``T``. The object is segmented
(:func:`softgrip_vision.segmentation.segment_object`) and its outline converted at the depth of its
own front face, as for a frame with the gripper in view; the fingers, which the frame does not
show, are the profile's, open, at that pose (:attr:`Scene.keypoints`).

The object's signed-distance grid is widened past the image where the gripper reaches (the fingers
hang from bases often above the view): the camera sees no object there, so none is assumed. Its
shape does not follow the pose: each side is a multiple of :data:`GRID_BUCKET_PX` that holds the
image and the reach around a pose anywhere in it (1024 x 1024 px for a 640 x 480 D405 frame at
120 mm), so new arm poses near the view, depths some mm apart or new frames of the same camera
compile the scoring programs no more; the padding holds the padded mask's own signed distance. An
object that runs off the image is warned about, since what lies beyond is unknown, and so is one that
a gripper already in view borders (segmented as light, unsaturated foreground), since it may hide
part of the object. A frame without an object is a scene without one (no contact); when the frame
seems to show one the thresholds missed (something in front of the background of neither the
object's nor the gripper's colour, or an object-coloured region without depth readings), that is
warned about (:func:`~softgrip_vision.segmentation.missing_object`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from jaxtyping import ArrayLike, Float

from softgrip_jax import SoftgripError
from softgrip_vision.coverage import edge_coverage
from softgrip_vision.frames import Frame, Intrinsics, load_frame, undistort_frame
from softgrip_vision.geometry import TILT_WARN_DEG, PlaneCamera, face_offset_mm
from softgrip_vision.keypoints import FingerKeypoints, Side
from softgrip_vision.object_sdf import object_sdf
from softgrip_vision.scene import MEMORY_PATH, FrameSceneError, ProfileLike, Scene, _default_warn
from softgrip_vision.segmentation import missing_object, segment_object

#: Tolerance of the rotation part of a gripper pose: |R^T R - I| and the last row's deviation.
ROTATION_TOLERANCE = 1e-3
#: A gripper pose nearer the camera than this (mm) is taken for a unit mistake (metres for mm).
MIN_DISTANCE_MM = 20.0
#: Default reach (mm) beyond the open fingers that the object's grid covers around the pose: the
#: poses a planner scores near it keep their bases on the grid.
DEFAULT_MARGIN_MM = 30.0
#: The grid is widened by at most this many times the image's size on each side (the gripper
#: reaching that far outside the image is taken for a unit mistake).
MAX_PAD_FACTOR = 2.0
#: The object grid's rows and columns are a multiple of this many pixels, enough for the gripper's
#: reach around a pose anywhere in the image: the arm poses a planner scores, depths some mm apart
#: included, give grids of one shape and compile the scoring programs once (``_widened_sdf``).
GRID_BUCKET_PX = 256
#: Object pixels within this many pixels of light, unsaturated foreground (a gripper in view) may
#: have part of the object hidden behind that foreground: warned about.
_HIDDEN_PX = 2


def gripper_plane(intrinsics: Intrinsics, gripper_pose: Float[ArrayLike, "4 4"],
                  source: str = "gripper_pose") -> tuple[PlaneCamera, np.ndarray]:
    """The gripper plane's camera and the gripper's pose in it from ``gripper_pose``, the 4 x 4
    transform (mm) from the gripper's frame to the camera's (module docstring).

    Returns:
        (camera, pose): the :class:`~softgrip_vision.geometry.PlaneCamera` of the plane through the
        fingers' centrelines, and (3,) float64 (x mm, y mm, angle rad) of the gripper in it.

    Raises:
        FrameSceneError: not a finite 4 x 4 rigid transform (a rotation and a translation in mm), a
            gripper behind the camera or seen from its back (mirrored), or a plane seen edge on.

    Example (a gripper 150 mm in front of the camera, 10 mm left and 40 mm up, turned 0.1 rad
    about the optical axis):
        >>> import numpy as np
        >>> from synthetic.render import d405_intrinsics
        >>> c, s = np.cos(0.1), np.sin(0.1)
        >>> T = np.array([[c, s, 0.0, -10.0], [-s, c, 0.0, -40.0], [0.0, 0.0, 1.0, 150.0], [0, 0, 0, 1]])
        >>> camera, pose = gripper_plane(d405_intrinsics(), T)
        >>> round(camera.depth_mm, 3), camera.normal, np.round(pose, 4).tolist()
        (150.0, (0.0, 0.0, 1.0), [-10.0, -40.0, 0.1])
    """
    try:
        t = np.asarray(gripper_pose, dtype=np.float64)
    except (TypeError, ValueError):
        t = np.empty(0)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise FrameSceneError(f"{source}: expected a finite 4 x 4 transform (mm) from the gripper's frame to the "
                              f"camera's, got {_describe(gripper_pose)}")
    rotation, translation = t[:3, :3], t[:3, 3]
    if (np.abs(t[3] - [0.0, 0.0, 0.0, 1.0]).max() > ROTATION_TOLERANCE
            or np.abs(rotation.T @ rotation - np.eye(3)).max() > ROTATION_TOLERANCE
            or np.linalg.det(rotation) <= 0):
        raise FrameSceneError(f"{source}: the transform is not rigid (its upper-left 3 x 3 block must be a rotation, "
                              f"orthonormal with determinant +1, and its last row 0 0 0 1); give the gripper's pose "
                              f"from the arm's forward kinematics and the hand-eye calibration")
    if translation[2] <= 0:
        raise FrameSceneError(f"{source}: the gripper is {translation[2]:g} mm along the optical axis, not in front "
                              f"of the camera (z must be > 0, in mm)")
    if np.linalg.norm(translation) < MIN_DISTANCE_MM:
        raise FrameSceneError(f"{source}: the gripper is {np.linalg.norm(translation):.3g} mm from the camera, nearer "
                              f"than any depth camera sees ({MIN_DISTANCE_MM:g} mm): give the translation in mm, "
                              f"not metres")
    normal = rotation[:, 2]
    if normal[2] <= 0:
        raise FrameSceneError(f"{source}: the gripper's z axis (x cross y: left-to-right base line cross base-to-tip) "
                              f"points toward the camera: the camera would see the gripper from its back, left and "
                              f"right mirrored; give the pose of the side the camera faces (turn x and z around)")
    tilt = math.degrees(math.acos(min(normal[2], 1.0)))
    if tilt >= 80.0:
        raise FrameSceneError(f"{source}: the gripper plane is seen nearly edge on ({tilt:.1f} degrees from facing "
                              f"the camera): its outline in the image carries no millimetres")
    depth = float(normal @ translation / normal[2])
    camera = PlaneCamera(intrinsics, depth, normal=(float(normal[0]), float(normal[1]), float(normal[2])))
    ex, ey, _ = camera.axes
    relative = translation - np.array([0.0, 0.0, depth])
    down = rotation[:, 1]
    angle = math.atan2(float(down @ ex), float(down @ ey))
    return camera, np.array([float(relative @ ex), float(relative @ ey), angle])


def open_fingers(camera: PlaneCamera, profile: ProfileLike, pose: np.ndarray) -> tuple[FingerKeypoints, FingerKeypoints]:
    """The profile's two fingers, open (straight, eq. 1 at zero closure), at ``pose`` (3,) = (x mm,
    y mm, angle rad), as :class:`~softgrip_vision.keypoints.FingerKeypoints` through ``camera``:
    what the frame would show of them.

    The bases and the direction the fingers hang are the core's (:func:`softgrip_jax.finger_frames`):
    each finger's centreline is the segment from its frame's origin along the frame's +y axis, its
    length long, sampled about 1 px apart (K points, K >= 2); pixel coordinates are float64.
    """
    import jax.numpy as jnp

    from softgrip_jax import finger_frames

    sides: tuple[Side, Side] = ("left", "right")
    gripper = profile.gripper()
    frames = finger_frames(gripper, np.asarray(pose, np.float64))
    out: list[FingerKeypoints] = []
    for side, frame, finger in zip(sides, frames, (gripper.left, gripper.right)):
        length = float(finger.length)
        steps = max(2, int(math.ceil(length / camera.mm_per_px)) + 1)  # about 1 px apart
        # On the finger's axis, base to tip; as many points for every depth of the plane near this
        # one (a multiple of 256), or JAX would compile to_world's small programs again for each.
        local = np.zeros((-(-steps // 256) * 256, 2), np.dtype(frame.origin.dtype))
        local[:steps, 1] = np.linspace(0.0, length, steps)
        centreline = np.asarray(frame.to_world(jnp.asarray(local)), np.float64)[:steps]
        centreline_px = camera.mm_to_px(centreline)
        out.append(FingerKeypoints(side=side, base_px=centreline_px[0], tip_px=centreline_px[-1],
                                   centreline_px=centreline_px,
                                   half_thickness_px=float(finger.half_thickness) / camera.mm_per_px,
                                   camera=camera, base_end="rounded", tip_end="rounded"))
    return out[0], out[1]


def object_scene(frame: str | os.PathLike[str] | Frame, profile: ProfileLike,
                 gripper_pose: Float[ArrayLike, "4 4"], *, margin_mm: float = DEFAULT_MARGIN_MM, settings=None,
                 warn: Callable[[str], None] | None = None) -> Scene:
    """A :class:`~softgrip_vision.scene.Scene` from a frame of the object alone and the gripper's
    pose in camera coordinates (module docstring).

    Args:
        frame: a frame folder, or a :class:`softgrip_vision.frames.Frame`; the gripper need not be in view.
        profile: the calibration profile (its fingers, base separation and segmentation settings).
        gripper_pose: (4, 4) transform (mm) from the gripper's frame to the camera's (the arm's
            forward kinematics composed with the hand-eye calibration).
        margin_mm: how far (mm) beyond the open fingers' reach around the pose the object's grid
            extends past the image (the candidate poses a planner scores near ``scene.pose``).
        settings: segmentation settings (the profile's when None).
        warn: called with each warning's text (default: :func:`warnings.warn` with a
            :class:`~softgrip_vision.scene.SceneWarning`).

    Raises:
        FrameSceneError: the frame cannot be read or segmented, or ``gripper_pose`` is not a usable
            pose (:func:`gripper_plane`); the message starts with the frame's path.

    Example (a rendered 30 mm disc, no gripper in view; the gripper 45 mm above it, facing the camera):
        >>> import numpy as np
        >>> from softgrip_calib.profile import load_profile
        >>> from softgrip_vision.samples import sample_data_dir
        >>> from synthetic.render import Scene, render, d405_intrinsics
        >>> a = np.linspace(0.0, 2.0 * np.pi, 128, endpoint=False)
        >>> disc = np.stack([15.0 * np.cos(a), 5.0 + 15.0 * np.sin(a)], axis=-1)  # mm, in a plane 120 mm deep
        >>> frame = render(Scene([], object_polygon=disc), d405_intrinsics())
        >>> T = np.eye(4); T[:3, 3] = [0.0, -40.0, 120.0]  # the arm's pose of the gripper, mm
        >>> scene = object_scene(frame, load_profile(sample_data_dir() / "sample_profile.json"), T)
        >>> print(scene.summary())
        frame in memory: gripper at x 0.0 mm, y -40.0 mm, angle 0.000 rad; object 29.9 x 30.2 mm; plane 120.0 mm deep
    """
    if not callable(getattr(profile, "gripper", None)):
        from softgrip_jax._checks import describe

        raise FrameSceneError(f"profile: got {describe(profile)}; pass a softgrip_calib.profile.CalibrationProfile: "
                              f"load_profile(path), or CalibrationProfile.from_dict(d) for a dict read from a profile")
    if not (isinstance(margin_mm, (int, float)) and math.isfinite(margin_mm) and margin_mm >= 0):
        raise FrameSceneError(f"margin_mm: expected a finite number of mm >= 0, got {margin_mm!r}")
    warn = warn or _default_warn
    label = MEMORY_PATH if isinstance(frame, Frame) else str(frame)
    settings = profile.segmentation_settings() if settings is None else settings
    try:
        loaded = undistort_frame(frame if isinstance(frame, Frame) else load_frame(frame))
        camera, pose = gripper_plane(loaded.intrinsics, gripper_pose)
        seg = segment_object(loaded, settings)
        offset = face_offset_mm(loaded, seg.object, camera)
        gripper = profile.gripper()
        longest = max(float(gripper.left.length), float(gripper.right.length))
        reach = longest + 0.5 * float(gripper.base_separation) + float(margin_mm)
        sdf = _widened_sdf(seg.object, camera.parallel(offset or 0.0), edge_coverage(loaded.color, seg.object),
                           pose[:2], reach)
    except SoftgripError as err:
        message = str(err)
        raise FrameSceneError(message if label in message else f"{label}: {message}") from None
    if camera.tilt_deg > TILT_WARN_DEG:
        warn(f"{label}: the gripper plane is tilted {camera.tilt_deg:.1f} degrees from facing the camera (more than "
             f"{TILT_WARN_DEG:g}): the object's outline loses accuracy")
    if seg.object.any():
        if offset is not None and abs(offset) > longest:
            warn(f"{label}: the object's front face lies {offset:.0f} mm {'behind' if offset > 0 else 'in front of'} "
                 f"the gripper plane, farther than a finger is long: check gripper_pose (mm, this camera's coordinates)")
        if offset is None:
            warn(f"{label}: the object has no depth readings: its outline is taken in the gripper plane")
        border = np.concatenate([seg.object[0], seg.object[-1], seg.object[:, 0], seg.object[:, -1]])
        if border.any():
            warn(f"{label}: the object runs off the image; beyond it no object is assumed: frame the whole object")
        near_gripper = cv2.dilate(np.asarray(seg.gripper, np.uint8), np.ones((2 * _HIDDEN_PX + 1,) * 2, np.uint8))
        if (near_gripper.view(bool) & seg.object).any():
            warn(f"{label}: part of the gripper is in view next to the object and may hide some of it: the "
                 f"outline there follows the gripper's edge; take the frame before the gripper covers the object")
    else:
        missed = missing_object(loaded, settings, seg)
        if missed is not None:
            warn(f"{label}: {missed}")
    keypoints = open_fingers(camera, profile, pose)
    seg = dataclasses.replace(seg, center_column=float(camera.mm_to_px(pose[:2])[0]))
    bases = np.stack([k.camera.px_to_mm(k.base_px) for k in keypoints])
    return Scene(path=label, frame=loaded, segmentation=seg, camera=camera, keypoints=keypoints,
                 bases_mm=bases, pose=pose, sdf=sdf, gripper=gripper)


def _widened_sdf(mask: np.ndarray, camera: PlaneCamera, coverage: np.ndarray, centre_mm: np.ndarray,
                 reach_mm: float):
    """:func:`~softgrip_vision.object_sdf.object_sdf` on the mask padded (no object) so that the grid
    covers the square of half-side ``reach_mm`` around ``centre_mm`` as well as the image.

    The grid's shape does not follow the pose: each side is the smallest multiple of
    :data:`GRID_BUCKET_PX` that holds the image and the square around any centre in the image
    (``max(n - 1, r) + r + 1`` px along a side of n px, r the reach in px at the optical axis), or,
    for a centre outside the image, the image and its square; the pixels beyond those are shared
    evenly between the two sides. The arm poses a planner scores near the view, depths some mm
    apart included, give one shape, so the scoring programs compiled for one serve them all. The
    padding holds the padded mask's own signed distance (the same computation as on the image):
    the value at a point (mm) does not depend on how far the grid extends."""
    h, w = mask.shape
    corners = centre_mm + reach_mm * np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
    px = camera.mm_to_px(corners)
    if not np.isfinite(px).all():
        raise FrameSceneError("the gripper's reach around its pose is not in view of the camera (behind it): "
                              "check gripper_pose")
    left, top = (max(0, math.ceil(-float(px[:, k].min()))) for k in (0, 1))
    right = max(0, math.ceil(float(px[:, 0].max()) - (w - 1)))
    bottom = max(0, math.ceil(float(px[:, 1].max()) - (h - 1)))
    if max(left, right) > MAX_PAD_FACTOR * w or max(top, bottom) > MAX_PAD_FACTOR * h:
        raise FrameSceneError(f"the gripper at this pose reaches far outside the image ({left}, {top}, {right}, "
                              f"{bottom} px beyond its left, top, right and bottom edges): check that gripper_pose "
                              f"is in mm and in this camera's coordinates")
    reach_px = math.ceil(reach_mm / camera.mm_per_px)
    (top, bottom), (left, right) = (_bucketed(n, before, after, reach_px)
                                    for n, before, after in ((h, top, bottom), (w, left, right)))
    pad = ((top, bottom), (left, right))
    i = camera.intrinsics
    wider = dataclasses.replace(i, width=w + left + right, height=h + top + bottom, ppx=i.ppx + left, ppy=i.ppy + top)
    return object_sdf(np.pad(mask, pad), dataclasses.replace(camera, intrinsics=wider),
                      coverage=np.pad(coverage, pad))


def _bucketed(n: int, before: int, after: int, reach_px: int) -> tuple[int, int]:
    """Padding (at least ``before``, at least ``after``) of a side of ``n`` px to the grid's size
    along it (:func:`_widened_sdf`), the extra shared evenly (the odd pixel after)."""
    needed = n + before + after
    size = -(-max(needed, max(n - 1, reach_px) + reach_px + 1) // GRID_BUCKET_PX) * GRID_BUCKET_PX
    extra = size - needed
    return before + extra // 2, after + extra - extra // 2


def _describe(value: Any) -> str:
    shape = getattr(value, "shape", None)
    return f"{type(value).__name__} of shape {tuple(shape)}" if shape is not None else repr(value)[:80]
