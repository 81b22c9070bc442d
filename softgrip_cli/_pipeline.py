"""Frame -> scene: the vision pipeline and the core's inputs, shared by ``estimate``, ``score`` and ``demo``.

One frame of the open gripper (and usually an object) becomes a :class:`FrameScene`:

1. the frame folder is loaded (``vision.frames.load_frame``) and segmented with the profile's
   segmentation settings;
2. the gripper is measured (``vision.measure.measure_gripper``, with the profile's ``vision``
   settings): the gripper plane fitted to the fingers' depth (tilt and front-surface relief), each
   finger's keypoints, and the depth of the object's front face;
3. each finger's base (plus the profile's base offset) gives the gripper's pose: the point midway
   between the two bases and the angle of the base line (0: the bases level, fingers hanging toward
   +y), in the gripper plane's millimetres (``PlaneCamera.px_to_mm``);
4. the object mask, at the depth of its front face, becomes the core's ``SDFGrid`` (no object reads
   "far");
5. the gripper is the profile's (``calib.profile.to_gripper``), optionally with each finger's length
   L measured in this frame (eq. 5).

The JSON helpers write one finger as the commands print it::

    {"side": "left"|"right", "valid": bool, "status": "ok"|"non_finite_input"|... (Status names),
     "case": "none"|"tip"|"tip_and_other"|"other", "theta_entire": rad,
     "joints_px": [[u, v], ...], "joints_mm": [[x, y], ...],    # N+1 joints, base (0) to tip (N)
     "contacts_px": [[u, v], ...], "contacts_mm": [[x, y], ...]}  # P_o1, and P_o2 for tip_and_other

Coordinates that are not finite (an invalid candidate outside the image) are written as null.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from softgrip_jax import CASE_NAMES, DEFAULT_METHOD, ContactCase, SoftgripError, Status

SIDES: tuple[str, str] = ("left", "right")
#: Warn when the frame's bases are this much closer or farther apart than the profile says (mm).
SEPARATION_WARN_MM = 3.0
#: Warn when an "open" finger is bent by more than this (rad, eq. 4 on the frame itself).
OPEN_BEND_WARN = 0.15


class FrameSceneError(SoftgripError):
    """A frame the pipeline cannot use; the message names the frame and what to do."""


def enable_compilation_cache() -> None:
    """Keep JAX's compiled programs on disk (``softgrip_jax.enable_compilation_cache`` with its default
    folder), so that the second run of a command starts in seconds. ``SOFTGRIP_JAX_CACHE=0`` turns it
    off. The command sets ``EQX_ON_ERROR=nan`` before equinox is imported (``softgrip_cli._main``), so
    its warning about equinox's checks only concerns a caller that imported equinox first: not shown."""
    import warnings

    from softgrip_jax import enable_compilation_cache as enable
    from softgrip_jax._cache import CacheWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CacheWarning)
        enable()


def warn(message: str) -> None:
    """One diagnostic line on stderr (stdout is reserved for results)."""
    print(f"warning: {message}", file=sys.stderr)


# ---------------------------------------------------------------------------------------------
# Profiles


def load_profile(path: str | os.PathLike[str]):
    """The calibration profile at ``path`` (``calib.profile.load_profile``; errors name the file)."""
    from calib.profile import load_profile as _load

    return _load(path)


def gripper_from_profile(profile, lengths_mm: tuple[float, float] | None = None):
    """The core's ``Gripper`` of a profile, with each finger's length replaced by ``lengths_mm``
    (left, right) when given."""
    import equinox as eqx
    import jax.numpy as jnp

    from calib.profile import to_gripper

    gripper = to_gripper(profile)
    if lengths_mm is not None:
        bad = [side for side, length in zip(SIDES, lengths_mm) if not (math.isfinite(length) and length > 0)]
        if bad:
            raise SoftgripError(f"the {bad[0]} finger's length measured in the frame is not a length > 0 mm")
        dtype = gripper.left.length.dtype
        gripper = eqx.tree_at(lambda g: (g.left.length, g.right.length), gripper,
                              tuple(jnp.asarray(length, dtype) for length in lengths_mm))
    return gripper


def segmentation_settings(profile):
    """The profile's :class:`~vision.segmentation.SegmentationSettings`."""
    from vision.segmentation import SegmentationSettings

    return SegmentationSettings.from_dict(profile.segmentation, source="the profile's segmentation")


# ---------------------------------------------------------------------------------------------
# Frame -> scene


@dataclass(frozen=True, eq=False)
class FrameScene:
    """Everything the core needs about one frame, and the vision results behind it.

    Attributes:
        path: the frame folder as given.
        frame: the loaded ``vision.frames.Frame``.
        segmentation: its ``vision.segmentation.Segmentation``.
        camera: the gripper plane's ``vision.geometry.PlaneCamera``.
        keypoints: (left, right) ``vision.keypoints.FingerKeypoints``.
        bases_mm: (2, 2) [left, right] finger bases, mm, with the profile's base offsets.
        pose: (3,) float64 (x mm, y mm, angle rad) of the gripper in the frame.
        sdf: the object's ``softgrip_jax.SDFGrid`` (mm).
        gripper: the ``softgrip_jax.Gripper`` to estimate with.
    """

    path: str
    frame: Any
    segmentation: Any
    camera: Any
    keypoints: tuple[Any, Any]
    bases_mm: np.ndarray
    pose: np.ndarray
    sdf: Any
    gripper: Any

    @property
    def name(self) -> str:
        """The frame folder's name (for output files)."""
        return Path(self.path).name or "frame"

    @property
    def has_object(self) -> bool:
        return bool(self.segmentation.object.any())

    @property
    def n_links(self) -> int:
        return int(self.gripper.left.n_links)


def pose_from_bases(left_mm: np.ndarray, right_mm: np.ndarray) -> np.ndarray:
    """(3,) pose (x mm, y mm, angle rad) of a gripper whose finger bases are at ``left_mm`` and
    ``right_mm``: their midpoint, and the rotation that takes the +x axis onto left -> right
    (the inverse of ``softgrip_jax.finger_frames``)."""
    left, right = np.asarray(left_mm, np.float64), np.asarray(right_mm, np.float64)
    centre = 0.5 * (left + right)
    d = right - left
    return np.array([centre[0], centre[1], math.atan2(-d[1], d[0])])


def frame_scene(path: str | os.PathLike[str], profile, *, length_from_frame: bool = False,
                settings=None) -> FrameScene:
    """Load, segment and measure one frame of the open gripper (see the module docstring).

    Args:
        path: a frame folder.
        profile: the ``calib.profile.CalibrationProfile``.
        length_from_frame: use each finger's length measured in this frame (eq. 5) instead of the
            profile's.
        settings: segmentation settings (the profile's when None).

    Raises:
        FrameSceneError: the frame cannot be read, segmented or measured; the message starts with
            the frame's path.
    """
    from vision.frames import load_frame
    from vision.measure import measure_gripper
    from vision.segmentation import segment

    label = str(path)
    settings = segmentation_settings(profile) if settings is None else settings
    try:
        frame = load_frame(path)
        seg = segment(frame, settings)
        measured = measure_gripper(frame, seg, profile.measure_settings())
        camera, keypoints = measured.camera, measured.keypoints
        sdf = measured.object_sdf(frame)
    except SoftgripError as err:
        message = str(err)
        raise FrameSceneError(message if label in message else f"{label}: {message}") from None
    for note in measured.warnings():
        warn(f"{label}: {note}")
    bases = profile.corrected_bases(np.stack([k.base_mm for k in keypoints]))
    pose = pose_from_bases(bases[0], bases[1])
    lengths = tuple(k.length_mm for k in keypoints) if length_from_frame else None
    try:
        gripper = gripper_from_profile(profile, lengths)
    except SoftgripError as err:
        raise FrameSceneError(f"{label}: {err}") from None
    recorded = (profile.camera or {}).get("intrinsics")
    if recorded and (recorded.get("width"), recorded.get("height")) != (frame.intrinsics.width,
                                                                        frame.intrinsics.height):
        warn(f"{label}: the frame is {frame.intrinsics.width}x{frame.intrinsics.height} px but the profile was "
             f"made with {recorded.get('width')}x{recorded.get('height')} px frames: is it the same camera setup?")
    separation = float(np.hypot(*(bases[1] - bases[0])))
    if abs(separation - profile.base_separation) > SEPARATION_WARN_MM:
        warn(f"{label}: the finger bases are {separation:.1f} mm apart but the profile says "
             f"{profile.base_separation:.1f} mm: is the profile for this gripper and camera distance?")
    try:
        bends = [k.theta for k in keypoints]
    except SoftgripError:  # a tip not below its base: eq. 4 is undefined
        warn(f"{label}: a finger's tip is not below its base; the estimate expects a frame of the open "
             f"gripper, fingers hanging down the image")
    else:
        if max(abs(b) for b in bends) > OPEN_BEND_WARN:
            warn(f"{label}: the fingers look bent ({bends[0]:.2f} and {bends[1]:.2f} rad by eq. 4); the "
                 f"estimate expects a frame of the open gripper before it closes")
    return FrameScene(path=label, frame=frame, segmentation=seg, camera=camera, keypoints=keypoints,
                      bases_mm=bases, pose=pose, sdf=sdf, gripper=gripper)


# ---------------------------------------------------------------------------------------------
# Compiled core calls, shared by every command in one process


_ESTIMATE = None


def estimate_grasp_jit():
    """``softgrip_jax.estimate_grasp`` compiled once (per frame size and N) for the whole process."""
    global _ESTIMATE
    if _ESTIMATE is None:
        import equinox as eqx

        from softgrip_jax import estimate_grasp

        _ESTIMATE = eqx.filter_jit(estimate_grasp)
    return _ESTIMATE


def estimate_scene(scene: FrameScene, method: str = DEFAULT_METHOD):
    """Both fingers' estimates at the frame's own pose, as numpy (a ``GraspEstimate``), with the
    deformation estimate ``method`` (``"geometric"`` or ``"mechanics"``)."""
    import jax.numpy as jnp

    dtype = scene.gripper.base_separation.dtype
    return to_numpy(estimate_grasp_jit()(scene.gripper, scene.sdf, jnp.asarray(scene.pose, dtype), method=method))


def to_numpy(tree):
    """Every array leaf of a PyTree as numpy (one device transfer)."""
    import jax

    return jax.device_get(tree)


def take(tree, index: int):
    """Element ``index`` of every leaf of a batched PyTree (numpy leaves)."""
    import jax

    return jax.tree_util.tree_map(lambda x: x[index], tree)


# ---------------------------------------------------------------------------------------------
# JSON


def points_json(points: np.ndarray, decimals: int) -> list:
    """(K, 2) points as [[a, b], ...], rounded, with null for non-finite coordinates."""
    out = []
    for row in np.asarray(points, np.float64).reshape(-1, 2):
        out.append([round(float(v), decimals) if math.isfinite(v) else None for v in row])
    return out


def number_json(value, decimals: int = 6):
    """A float rounded, or null when not finite."""
    value = float(value)
    return round(value, decimals) if math.isfinite(value) else None


def finger_contacts_mm(estimate) -> np.ndarray:
    """(P, 2) contact points on the object, mm: none for case (a), P_o1, and P_o2 for case (c)."""
    case = int(estimate.case)
    if case == ContactCase.NONE:
        return np.zeros((0, 2))
    points = [np.asarray(estimate.contact.p_o1, np.float64)]
    if case == ContactCase.TIP_AND_OTHER:
        points.append(np.asarray(estimate.contact.p_o2, np.float64))
    return np.stack(points)


def finger_json(side: str, estimate, finger, camera) -> dict:
    """One finger's fields (see the module docstring) from a numpy ``Estimate``."""
    joints_mm = np.asarray(estimate.joints, np.float64)
    contacts_mm = finger_contacts_mm(estimate)
    return {
        "side": side,
        "valid": bool(estimate.valid),
        "status": status_name(estimate.status),
        "case": CASE_NAMES[int(estimate.case)],
        "theta_entire": round(float(finger.theta_entire), 6),
        "joints_px": points_json(camera.mm_to_px(joints_mm), 3),
        "joints_mm": points_json(joints_mm, 4),
        "contacts_px": points_json(camera.mm_to_px(contacts_mm), 3),
        "contacts_mm": points_json(contacts_mm, 4),
    }


def fingers_json(grasp, gripper, camera) -> list[dict]:
    """[left, right] finger fields of a numpy ``GraspEstimate``."""
    return [finger_json(side, getattr(grasp, side), getattr(gripper, side), camera) for side in SIDES]


def frame_json(scene: FrameScene, grasp, method: str) -> dict:
    """``{"frame", "valid", "status", "method", "n_links", "fingers"}``: one line of ``softgrip
    estimate --json`` (``method``: the deformation estimate used). The frame is valid when both
    fingers are; its status is the first invalid finger's (``"ok"`` when both are valid)."""
    fingers = fingers_json(grasp, scene.gripper, scene.camera)
    bad = [f for f in fingers if not f["valid"]]
    return {"frame": scene.path, "valid": not bad, "status": bad[0]["status"] if bad else "ok", "method": method,
            "n_links": scene.n_links, "fingers": fingers}


def failed_frame_json(path: str, method: str, error: str) -> dict:
    """The ``softgrip estimate --json`` line of a frame that could not be estimated at all."""
    return {"frame": path, "valid": False, "status": "error", "error": error, "method": method, "n_links": None,
            "fingers": []}


def pose_json(pose: np.ndarray) -> dict:
    return {"x_mm": round(float(pose[0]), 4), "y_mm": round(float(pose[1]), 4),
            "angle_rad": round(float(pose[2]), 6)}


def status_name(status: int, penetrating: bool = False) -> str:
    """A candidate's status as JSON text: ``softgrip_jax.Status`` names in lower case, or
    ``"penetrating"`` for an estimate that is usable but flagged by the score."""
    status = int(status)
    if status == 0 and penetrating:
        return "penetrating"
    try:
        return Status(status).name.lower()
    except ValueError:
        return f"status_{status}"


def components_json(components) -> dict:
    """Score components (a numpy ``ScoreComponents``) as {name: number or [left, right]}."""
    import dataclasses

    out = {}
    for field in dataclasses.fields(components):
        value = np.asarray(getattr(components, field.name), np.float64)
        out[field.name] = number_json(value) if value.ndim == 0 else [number_json(v) for v in value.ravel()]
    return out


def candidate_json(pose: np.ndarray, scored, gripper, camera) -> dict:
    """One scored candidate (a numpy ``Score`` of one pose) as ``softgrip score`` prints it."""
    valid = bool(scored.valid)
    return {
        "pose": pose_json(pose),
        "score": number_json(scored.score) if valid else None,
        "components": components_json(scored.components),
        "valid": valid,
        "status": status_name(scored.status, bool(scored.penetrating)),
        "fingers": fingers_json(scored.grasp, gripper, camera),
    }


# ---------------------------------------------------------------------------------------------
# Pictures


def grasp_overlay(rgb: np.ndarray, grasp, camera, observed_px=(), label: str | None = None) -> np.ndarray:
    """``rgb`` with both fingers' estimated joints (blue), contacts (red) and observed positions
    (green, (K, 2) px each) drawn as in the paper's Figs. 15-17, with white halos so they read on
    any background, and an optional caption."""
    from vision.overlay import draw_overlay

    joints = [camera.mm_to_px(np.asarray(getattr(grasp, side).joints, np.float64)) for side in SIDES]
    contacts = np.concatenate([camera.mm_to_px(finger_contacts_mm(getattr(grasp, side))) for side in SIDES])
    image = rgb.copy()
    for points in joints:
        finite = np.isfinite(points).all(axis=1)
        if finite.sum() >= 2:
            cv2.polylines(image, [np.rint(points[finite] * 16).astype(np.int32)], False, (255, 255, 255), 5,
                          cv2.LINE_AA, 4)
    for point in contacts:
        if np.isfinite(point).all():
            cv2.circle(image, tuple(np.rint(point * 16).astype(int)), 7 * 16, (255, 255, 255), -1, cv2.LINE_AA, 4)
    if len(observed_px):  # observed first, so that the estimate is drawn over it
        image = draw_overlay(image, observed=list(observed_px), radius_px=5)
    image = draw_overlay(image, joints=joints, contacts=contacts, radius_px=3, thickness_px=2)
    if label:
        caption(image, label, (8, 8))
    return image


def caption(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45,
            bottom: bool = False) -> None:
    """Write lines of ``text`` in white on a dark box, in place: ``origin`` is the box's top-left
    corner (px), or its bottom-left corner with ``bottom=True``."""
    lines = text.splitlines()
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1
    sizes = [cv2.getTextSize(line, font, scale, thick)[0] for line in lines]
    step = max(h for _, h in sizes) + 6
    width = max(w for w, _ in sizes) + 8
    x, y = origin
    if bottom:
        y = max(0, y - step * len(lines) - 4)
    box = image[y:y + step * len(lines) + 4, x:x + width]
    box[:] = (0.35 * box).astype(np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(image, line, (x + 4, y + step * (k + 1) - 2), font, scale, (255, 255, 255), thick, cv2.LINE_AA)


def unique_png_names(scenes_paths: list[str]) -> list[str]:
    """``<frame-name>.png`` for each frame path, made unique with ``_2``, ``_3``, ... on repeats."""
    seen: dict[str, int] = {}
    names = []
    for path in scenes_paths:
        stem = Path(path).name or "frame"
        seen[stem] = seen.get(stem, 0) + 1
        names.append(f"{stem}.png" if seen[stem] == 1 else f"{stem}_{seen[stem]}.png")
    return names


def check_output_file(path: str | os.PathLike[str], what: str, inputs=(), force: bool = False) -> Path:
    """Refuse, before any work, an output file ``path`` that cannot or must not be written (the
    output policy of ``vision.atomic_write``: one of the command's ``inputs``, a folder, a FIFO or
    device, a link or read-only file without ``force``), or one whose folder does not exist (the
    message names ``what``, e.g. ``"-o"``, and the path)."""
    from vision.atomic_write import check_output

    target = check_output(path, inputs=inputs, force=force, what=what)
    if not target.parent.is_dir():
        raise SoftgripError(f"{what} {path}: the folder {target.parent} does not exist (or is not a folder); "
                            f"create it first")
    return Path(path)


def frame_inputs(*folders) -> list[Path]:
    """The input files of frame ``folders`` (for the output policy)."""
    from vision.atomic_write import frame_inputs as _files

    return [path for folder in folders if folder is not None for path in _files(folder)]


def add_force_argument(parser) -> None:
    """``--force``: the output policy's permission to replace through links and read-only files."""
    parser.add_argument("--force", action="store_true",
                        help="replace an output file even when it is read-only, or a symbolic link (then the "
                             "file it points to is replaced and the link kept); inputs, folders, FIFOs and "
                             "devices are never replaced")


def ensure_dir(path: str | os.PathLike[str], what: str) -> Path:
    """Create folder ``path`` (and parents) or raise a ``SoftgripError`` naming it."""
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SoftgripError(f"cannot create the {what} {folder}: {err.strerror}") from None
    if not folder.is_dir():
        raise SoftgripError(f"the {what} {folder} is not a folder")
    return folder
