"""Frame -> scene -> results: the public API a planner calls with an RGB-D frame and a profile.

One frame of the open gripper (and usually an object) becomes a :class:`Scene`
(:func:`frame_scene`):

1. the frame folder is loaded (:func:`softgrip_vision.frames.load_frame`; or a :class:`~softgrip_vision.frames.Frame`
   built in memory from numpy arrays) and segmented with the profile's segmentation settings;
2. the gripper is measured (:func:`softgrip_vision.measure.measure_gripper`, with the profile's ``softgrip_vision``
   settings): the gripper plane fitted to the fingers' depth (tilt and front-surface relief), each
   finger's keypoints, and the depth of the object's front face;
3. each finger's base (plus the profile's base offset) gives the gripper's pose: the point midway
   between the two bases and the angle of the base line (0: the bases level, fingers hanging toward
   +y), in the gripper plane's millimetres (:meth:`~softgrip_vision.geometry.PlaneCamera.px_to_mm`);
4. the object mask, at the depth of its front face, becomes the core's
   :class:`~softgrip_jax.SDFGrid` (no object reads "far");
5. the gripper is the profile's (:meth:`softgrip_calib.profile.CalibrationProfile.gripper`), optionally with
   each finger's length L measured in this frame (eq. 5).

A scene then answers for any poses (numpy or JAX, (3,) or (B, 3): x mm, y mm, angle rad):
:meth:`Scene.estimate` (both fingers' estimates) and :meth:`Scene.score` (ranked-ready scores), as
numpy. :attr:`Scene.conventions` says in which frame all of it is (origin, axes, units, the plane's
depth); :mod:`softgrip_vision.documents` writes the same results as the JSON documents of ``softgrip
estimate --json`` and ``softgrip score --json``.

The profile is anything with the methods of :class:`ProfileLike` (a
:class:`softgrip_calib.profile.CalibrationProfile` has them): ``softgrip_vision`` does not import ``softgrip_calib``.

Example (the README's "From a frame to a scene"; ``tests/test_readme.py`` keeps the two identical):
    >>> import numpy as np
    >>> from softgrip_calib.profile import load_profile
    >>> from softgrip_jax import Geometric
    >>> from softgrip_vision.samples import sample_data_dir
    >>> from softgrip_vision.scene import frame_scene, rank
    >>> data = sample_data_dir()  # the sample frames and profile, shipped with the package
    >>> scene = frame_scene(data / "circle_open", load_profile(data / "sample_profile.json"))
    >>> print(scene.summary())
    circle_open: gripper at x 0.0 mm, y -45.1 mm, angle -0.001 rad; object 29.3 x 29.3 mm; plane 120.0 mm deep
    >>> print(scene.conventions["axes"], "| plane depth (mm):", round(scene.conventions["plane"]["depth_mm"], 1))
    x to the right and y down, as the image's u and v, in the gripper plane | plane depth (mm): 120.0
    >>> print({side: np.round(f["base_mm"], 1).tolist() for side, f in scene.finger_frames.items()})
    {'left': [-32.0, -45.1], 'right': [32.0, -45.0]}
    >>> # Both fingers at the frame's own pose; the first estimate compiles (seconds), later ones do not.
    >>> grasp = scene.estimate(estimator=Geometric())
    >>> for side in ("left", "right"):
    ...     f = getattr(grasp, side)
    ...     print(side, scene.case_name(grasp, side), "tip (mm):", [round(float(v), 1) for v in f.joints[-1]])
    left other tip (mm): [-6.9, -2.2]
    right other tip (mm): [7.1, -2.0]
    >>> # Candidate poses as numpy (B, 3): x mm, y mm, angle rad; here the frame's pose, 4 mm left, 80 mm up.
    >>> poses = scene.pose + np.array([[0.0, 0.0, 0.0], [-4.0, 0.0, 0.0], [0.0, -80.0, 0.0]])
    >>> result = scene.score(poses, estimator=Geometric())  # numpy out; -inf where not valid
    >>> print(rank(result).tolist(), [round(float(v), 3) for v in result.score], result.valid.tolist())
    [0, 1, 2] [0.196, 0.194, -inf] [True, True, False]
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from jaxtyping import ArrayLike, Float

from softgrip_jax import CASE_NAMES, AbstractEstimator, Gripper, SoftgripError, as_estimator
from softgrip_vision.frames import Frame

if TYPE_CHECKING:
    from softgrip_jax import GraspEstimate, Refined, Score, ScoreWeights, SDFGrid, Uncertainty
    from softgrip_vision.geometry import PlaneCamera
    from softgrip_vision.keypoints import FingerKeypoints
    from softgrip_vision.segmentation import Segmentation

SIDES: tuple[str, str] = ("left", "right")
#: Warn when the frame's bases are this much closer or farther apart than the profile says (mm).
SEPARATION_WARN_MM = 3.0
#: Warn when an "open" finger is bent by more than this (rad, eq. 4 on the frame itself).
OPEN_BEND_WARN = 0.15
#: A frame whose fingers are both bent by more than this fraction of the profile's full closure
#: (theta_entire) shows the closed gripper, not the open one the estimate starts from: refused.
CLOSED_FRACTION = 0.5
#: :attr:`Scene.path` of a frame built in memory (no folder), and the name its titles show.
MEMORY_PATH = "<memory>"
MEMORY_NAME = "frame in memory"


class FrameSceneError(SoftgripError):
    """A frame the pipeline cannot use; the message names the frame and what to do."""


class SceneWarning(UserWarning):
    """Something about a frame that may make its estimate wrong (a bent "open" finger, bases
    farther apart than the profile says, a different camera resolution, a tilted plane, ...)."""


class ProfileLike(Protocol):
    """What :func:`frame_scene` needs of a calibration profile
    (:class:`softgrip_calib.profile.CalibrationProfile`)."""

    @property
    def base_separation(self) -> float: ...
    @property
    def camera(self) -> dict[str, Any]: ...

    def segmentation_settings(self) -> Any: ...
    def measure_settings(self) -> Any: ...
    def corrected_bases(self, bases_mm: Any) -> np.ndarray: ...
    def gripper(self) -> Gripper: ...


def pose_from_bases(left_mm: Any, right_mm: Any) -> np.ndarray:
    """(3,) pose (x mm, y mm, angle rad) of a gripper whose finger bases are at ``left_mm`` and
    ``right_mm``: their midpoint, and the rotation that takes the +x axis onto left -> right
    (the inverse of :func:`softgrip_jax.finger_frames`).

    Example:
        >>> pose_from_bases([-32.0, 5.0], [32.0, 5.0]).tolist()
        [0.0, 5.0, -0.0]
    """
    left, right = np.asarray(left_mm, np.float64), np.asarray(right_mm, np.float64)
    centre = 0.5 * (left + right)
    d = right - left
    return np.array([centre[0], centre[1], math.atan2(-d[1], d[0])])


def with_lengths(gripper: Gripper, lengths_mm: tuple[float, float] | None) -> Gripper:
    """``gripper`` with each finger's length replaced by ``lengths_mm`` (left, right), when given."""
    if lengths_mm is None:
        return gripper
    import equinox as eqx
    import jax.numpy as jnp

    bad = [side for side, length in zip(SIDES, lengths_mm) if not (math.isfinite(length) and length > 0)]
    if bad:
        raise SoftgripError(f"the {bad[0]} finger's length measured in the frame is not a length > 0 mm")
    dtype = gripper.left.length.dtype
    return eqx.tree_at(lambda g: (g.left.length, g.right.length), gripper,
                       tuple(jnp.asarray(length, dtype) for length in lengths_mm))


# ---------------------------------------------------------------------------------------------
# Compiled core calls, shared by every scene in one process

_ESTIMATE = None


def _estimate_grasp_jit():
    """``softgrip_jax.estimate_grasp`` compiled once (per frame size and N) for the whole process."""
    global _ESTIMATE
    if _ESTIMATE is None:
        import equinox as eqx

        from softgrip_jax import estimate_grasp

        _ESTIMATE = eqx.filter_jit(estimate_grasp)
    return _ESTIMATE


def _poses(poses: Any, what: str) -> np.ndarray:
    """(B, 3) float64 poses from (3,) or (B, 3) numbers; a SoftgripError naming ``what`` otherwise."""
    array = np.asarray(poses, np.float64)
    if array.ndim == 1:
        array = array[None]
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < 1:
        raise SoftgripError(f"{what}: expected poses of shape (3,) or (B, 3) (x mm, y mm, angle rad), got "
                            f"shape {np.shape(poses)}")
    return array


def to_numpy(tree):
    """Every array leaf of a PyTree as numpy (one device transfer)."""
    import jax

    return jax.device_get(tree)


def take(tree, index: int):
    """Element ``index`` of every leaf of a batched PyTree (numpy leaves)."""
    import jax

    return jax.tree_util.tree_map(lambda x: x[index], tree)


# ---------------------------------------------------------------------------------------------
# The scene


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything the core needs about one frame, and the vision results behind it.

    Attributes:
        path: the frame folder as given (:data:`MEMORY_PATH`, ``"<memory>"``, for a frame built in memory).
        frame: the :class:`softgrip_vision.frames.Frame` (colour, depth, intrinsics), with the lens distortion
            undone (:func:`softgrip_vision.frames.undistort_frame`): the pixels everything else refers to.
        segmentation: its :class:`softgrip_vision.segmentation.Segmentation` (gripper, fingers, object masks).
        camera: the gripper plane's :class:`softgrip_vision.geometry.PlaneCamera` (px <-> mm).
        keypoints: (left, right) :class:`softgrip_vision.keypoints.FingerKeypoints`.
        bases_mm: (2, 2) [left, right] finger bases, mm, with the profile's base offsets.
        pose: (3,) float64 (x mm, y mm, angle rad) of the gripper in the frame.
        sdf: the object's :class:`softgrip_jax.SDFGrid` (mm).
        gripper: the :class:`softgrip_jax.Gripper` to estimate with.
    """

    path: str
    frame: Frame
    segmentation: Segmentation
    camera: PlaneCamera
    keypoints: tuple[FingerKeypoints, FingerKeypoints]
    bases_mm: Float[np.ndarray, "2 2"]
    pose: Float[np.ndarray, "3"]
    sdf: SDFGrid
    gripper: Gripper

    @property
    def name(self) -> str:
        """The frame folder's name (for output files and titles); :data:`MEMORY_NAME` for a frame
        built in memory."""
        if self.path == MEMORY_PATH:
            return MEMORY_NAME
        return Path(self.path).name or "frame"

    @property
    def has_object(self) -> bool:
        return bool(self.segmentation.object.any())

    @property
    def n_links(self) -> int:
        return int(self.gripper.left.n_links)

    @property
    def finger_frames(self) -> dict[str, dict[str, Any]]:
        """Each finger's frame at the scene's pose, in mm: ``{"left": {"base_mm": [x, y],
        "angle_rad": a, "handedness": 1.0}, "right": {..., "handedness": -1.0}}`` (the right finger
        curls toward -x: it is the left computation mirrored, :func:`softgrip_jax.finger_frames`)."""
        return self.finger_frames_at(self.pose)

    def finger_frames_at(self, pose: Any) -> dict[str, dict[str, Any]]:
        """:attr:`finger_frames` at another ``pose`` (x mm, y mm, angle rad)."""
        from softgrip_jax import finger_frames

        frames = to_numpy(finger_frames(self.gripper, np.asarray(pose, np.float64)))
        return {side: {"base_mm": [float(v) for v in f.origin], "angle_rad": float(f.angle),
                       "handedness": float(f.handedness)} for side, f in zip(SIDES, frames)}

    @property
    def conventions(self) -> dict[str, Any]:
        """The frame every millimetre of this scene (and of its results) is in, as a JSON-ready dict:
        ``units``, ``origin``, ``axes``, ``angle``, ``pose`` and ``plane`` (its depth on the optical
        axis, its normal and tilt in camera coordinates)."""
        return conventions(self.camera)

    def summary(self) -> str:
        """One line: the frame's name, the gripper's pose, the object's size and the plane's depth."""
        x, y, angle = (round(float(v), d) + 0.0 for v, d in zip(self.pose, (1, 1, 3)))  # + 0.0: never "-0.0"
        text = f"{self.name}: gripper at x {x:.1f} mm, y {y:.1f} mm, angle {angle:.3f} rad; "
        if self.has_object:
            rows, cols = np.nonzero(self.segmentation.object)
            (x0, y0), (x1, y1) = self.camera.px_to_mm([[cols.min() - 0.5, rows.min() - 0.5],
                                                       [cols.max() + 0.5, rows.max() + 0.5]])
            text += f"object {x1 - x0:.1f} x {y1 - y0:.1f} mm; "
        else:
            text += "no object; "
        return text + f"plane {self.camera.depth_mm:.1f} mm deep"

    def estimate(self, poses: Float[ArrayLike, "*b 3"] | None = None, *,
                 estimator: AbstractEstimator | None = None) -> GraspEstimate:
        """Both fingers' estimates, as numpy (a :class:`softgrip_jax.GraspEstimate`).

        Args:
            poses: None (the frame's own pose), one pose (3,) or B poses (B, 3), numpy or JAX:
                x mm, y mm, angle rad.
            estimator: the deformation estimate, ``softgrip_jax.Geometric()`` or
                ``softgrip_jax.Mechanics(config)`` (None: ``Mechanics()``).

        Returns:
            For None or one pose, one ``GraspEstimate`` (joints (N+1, 2) mm per finger); for (B, 3),
            leaves with a leading axis B.
        """
        import jax.numpy as jnp

        estimator = as_estimator(estimator)
        dtype = self.gripper.base_separation.dtype
        if poses is None or np.ndim(poses) == 1:
            pose = _poses(self.pose if poses is None else poses, "Scene.estimate")[0]
            return to_numpy(_estimate_grasp_jit()(self.gripper, self.sdf, jnp.asarray(pose, dtype),
                                                     estimator=estimator))
        from softgrip_jax import estimate_grasp_batch

        batch = _poses(poses, "Scene.estimate")
        return to_numpy(estimate_grasp_batch(self.gripper, self.sdf, batch.astype(dtype), estimator=estimator))

    def score(self, poses: Float[ArrayLike, "*b 3"], *, estimator: AbstractEstimator | None = None,
              weights: ScoreWeights | None = None,
              uncertainty: Uncertainty | None = None,
              progress: Callable[[int, int], None] | None = None) -> Score:
        """Score poses (numpy or JAX, (3,) or (B, 3): x mm, y mm, angle rad) in one compiled call.

        ``estimator`` is as for :meth:`estimate`. Every batch size runs
        through one compiled program (:func:`softgrip_jax.score` evaluates pieces of one size);
        ``progress(done, total)`` is called after each piece. ``weights``: a
        :class:`softgrip_jax.ScoreWeights` (None: the defaults), e.g.
        ``ScoreWeights(mu=0.8)`` for another friction coefficient; its values are run-time, so
        changing them never recompiles. Returns a :class:`softgrip_jax.Score` with numpy leaves of
        leading axis B (``score`` is -inf where not valid; ``quality``, ``force_closure`` and the
        ``contacts`` the quality comes from); rank with :func:`rank`. ``uncertainty``: a
        :class:`softgrip_jax.Uncertainty` for robust quality (``quality_mean``, ``p_closure``).
        """
        import jax
        import jax.numpy as jnp

        from softgrip_jax import ScoreWeights, score

        weights = ScoreWeights() if weights is None else weights
        if not isinstance(weights, ScoreWeights):
            raise SoftgripError(f"Scene.score: weights must be a softgrip_jax.ScoreWeights (e.g. "
                                f"ScoreWeights(mu=0.5)), got {type(weights).__name__}")
        batch = _poses(poses, "Scene.score")
        # numpy poses: the core splits them into pieces on the host (jnp.asarray of a new batch
        # size would compile a small program for it).
        result = jax.block_until_ready(score(self.gripper, self.sdf, batch.astype(self.gripper.base_separation.dtype),
                                             weights, estimator=as_estimator(estimator),
                                             uncertainty=uncertainty, progress=progress))
        return to_numpy(result)

    def refine(self, poses: Float[ArrayLike, "*b 3"] | None = None, *, estimator: AbstractEstimator | None = None,
               weights: ScoreWeights | None = None, uncertainty: Uncertainty | None = None, max_steps: int = 32,
               progress: Callable[[int, int], None] | None = None) -> Refined:
        """Improve poses by a compass search of the score (:func:`softgrip_jax.refine` on this
        scene's gripper and object), in the coordinates :meth:`score` takes: x mm, y mm, angle rad.

        Args:
            poses: None (the frame's own pose), one pose (3,) or B poses (B, 3), numpy or JAX,
                e.g. the best rows of a :meth:`score`.
            estimator: as for :meth:`score`.
            weights: as for :meth:`score`.
            uncertainty: as for :meth:`score`.
            max_steps: stencil polls of the compass search at most (a new value compiles once more).
            progress: ``progress(done, total)`` after each piece of a batch.

        Returns:
            A :class:`softgrip_jax.Refined` with numpy leaves (leading axis B for a batch): the
            ``pose``, its ``score`` (a :class:`softgrip_jax.Score`), the ``start_score`` and the
            ``status`` (a :class:`softgrip_jax.RefineStatus`); never worse than the start.
        """
        from softgrip_jax import ScoreWeights, refine

        weights = ScoreWeights() if weights is None else weights
        if not isinstance(weights, ScoreWeights):
            raise SoftgripError(f"Scene.refine: weights must be a softgrip_jax.ScoreWeights (e.g. "
                                f"ScoreWeights(mu=0.5)), got {type(weights).__name__}")
        dtype = self.gripper.base_separation.dtype
        batch = _poses(self.pose if poses is None else poses, "Scene.refine").astype(dtype)
        start = batch if poses is not None and np.ndim(poses) == 2 else batch[0]
        return to_numpy(refine(self.gripper, self.sdf, start, weights, estimator=as_estimator(estimator),
                               uncertainty=uncertainty, max_steps=max_steps, progress=progress))

    @staticmethod
    def case_name(grasp: GraspEstimate, side: str) -> str:
        """The contact case of finger ``side`` of a single (unbatched) estimate, by name."""
        return CASE_NAMES[int(getattr(grasp, side).case)]


#: The old name of :class:`Scene`.
FrameScene = Scene


def take_rows(tree, count: int):
    """The first ``count`` rows of every leaf of a batched PyTree (numpy leaves)."""
    import jax

    return jax.tree_util.tree_map(lambda x: x[:count], tree)


def rank(result: Score) -> np.ndarray:
    """Candidate indices of a :class:`softgrip_jax.Score`, best first; invalid candidates last, each
    group in input order."""
    key = np.where(np.asarray(result.valid) & np.isfinite(result.score), result.score, -np.inf)
    return np.argsort(-key, kind="stable")


def conventions(camera=None) -> dict[str, Any]:
    """The coordinate conventions of results measured with ``camera`` (a
    :class:`~softgrip_vision.geometry.PlaneCamera`), as written into every JSON document. Without a camera
    (a document of several frames), ``plane`` says that each frame gives its own."""
    plane: Any = "each frame's own: its depth_mm, normal and tilt_deg under frames[].plane"
    if camera is not None:
        plane = {"depth_mm": round(float(camera.depth_mm), 4),
                 "normal": [round(float(c), 6) for c in camera.normal],
                 "tilt_deg": round(float(camera.tilt_deg), 3)}
    return {
        "units": {"length": "mm", "angle": "rad", "image": "px"},
        "origin": "where the camera's optical axis meets the gripper plane (the plane through the fingers' "
                  "centrelines); pixel coordinates: the centre of the top-left pixel is (0, 0)",
        "axes": "x to the right and y down, as the image's u and v, in the gripper plane",
        "angle": "radians from the downward vertical (+y), positive toward +x",
        "pose": "gripper pose (x_mm, y_mm, angle_rad): the point midway between the two finger bases and the "
                "gripper's in-plane rotation (0: fingers hanging toward +y)",
        "plane": plane,
    }


def _default_warn(message: str) -> None:
    warnings.warn(message, SceneWarning, stacklevel=3)


def frame_scene(frame: str | os.PathLike[str] | Frame, profile: ProfileLike, *, length_from_frame: bool = False,
                settings=None, warn: Callable[[str], None] | None = None) -> Scene:
    """Load, segment and measure one frame of the open gripper (see the module docstring).

    Args:
        frame: a frame folder, or a :class:`softgrip_vision.frames.Frame` (numpy colour, depth and intrinsics).
        profile: the calibration profile (:class:`softgrip_calib.profile.CalibrationProfile`).
        length_from_frame: use each finger's length measured in this frame (eq. 5) instead of the
            profile's.
        settings: segmentation settings (the profile's when None).
        warn: called with each warning's text (default: :func:`warnings.warn` with a
            :class:`SceneWarning`).

    Raises:
        FrameSceneError: the frame cannot be read, segmented or measured, or its gripper does not
            match the profile (finger length, thickness, base separation:
            :func:`softgrip_vision.plausibility.check_profile_match`, which names the profile by its
            ``source`` attribute when it has one); the message starts with the frame's path.
    """
    from softgrip_vision.frames import load_frame, undistort_frame
    from softgrip_vision.measure import measure_gripper
    from softgrip_vision.segmentation import segment

    if isinstance(profile, (dict, str, os.PathLike)) or not callable(getattr(profile, "gripper", None)):
        from softgrip_jax._checks import describe

        raise FrameSceneError(f"profile: got {describe(profile)}; pass a softgrip_calib.profile.CalibrationProfile: "
                              f"load_profile(path), or CalibrationProfile.from_dict(d) for a dict read from a profile")
    warn = warn or _default_warn
    label = MEMORY_PATH if isinstance(frame, Frame) else str(frame)
    settings = profile.segmentation_settings() if settings is None else settings
    try:
        # Lens distortion undone once, before anything is measured: the scene's frame is the pinhole one.
        loaded = undistort_frame(frame if isinstance(frame, Frame) else load_frame(frame))
        seg = segment(loaded, settings)
        measured = measure_gripper(loaded, seg, profile.measure_settings())
        camera, keypoints = measured.camera, measured.keypoints
        sdf = measured.object_sdf(loaded)
    except SoftgripError as err:
        message = str(err)
        raise FrameSceneError(message if label in message else f"{label}: {message}") from None
    for note in measured.warnings():
        warn(f"{label}: {note}")
    if not seg.object.any():
        from softgrip_vision.segmentation import missing_object

        missed = missing_object(loaded, settings, seg)
        if missed is not None:
            warn(f"{label}: {missed}")
    bases = profile.corrected_bases(np.stack([k.base_mm for k in keypoints]))
    pose = pose_from_bases(bases[0], bases[1])
    lengths: tuple[float, float] | None = ((keypoints[0].length_mm, keypoints[1].length_mm) if length_from_frame
                                           else None)
    try:
        gripper = with_lengths(profile.gripper(), lengths)
    except SoftgripError as err:
        raise FrameSceneError(f"{label}: {err}") from None
    intrinsics = loaded.intrinsics
    recorded = (profile.camera or {}).get("intrinsics")
    if recorded and (recorded.get("width"), recorded.get("height")) != (intrinsics.width, intrinsics.height):
        warn(f"{label}: the frame is {intrinsics.width}x{intrinsics.height} px but the profile was "
             f"made with {recorded.get('width')}x{recorded.get('height')} px frames: is it the same camera setup?")
    separation = float(np.hypot(*(bases[1] - bases[0])))
    if hasattr(profile, "fingers"):  # a CalibrationProfile: its sizes against the frame's
        from softgrip_vision.plausibility import check_orientation_against_calibration, check_profile_match

        try:
            if not recorded or (recorded.get("width"), recorded.get("height")) == (intrinsics.width, intrinsics.height):
                detected = (getattr(profile, "vision", None) or {}).get("detected") or {}
                check_orientation_against_calibration(keypoints, detected.get("open"),
                                                      (intrinsics.width, intrinsics.height), source=label,
                                                      profile_source=getattr(profile, "source", None) or "the profile")
            check_profile_match(keypoints, separation, profile, source=label,
                                profile_source=getattr(profile, "source", None) or "the profile",
                                lengths=not length_from_frame)
        except SoftgripError as err:
            raise FrameSceneError(str(err)) from None
    if abs(separation - profile.base_separation) > SEPARATION_WARN_MM:
        warn(f"{label}: the finger bases are {separation:.1f} mm apart but the profile says "
             f"{profile.base_separation:.1f} mm: is the profile for this gripper and camera distance?")
    try:
        bends = [k.theta for k in keypoints]
    except SoftgripError:  # a tip not below its base: eq. 4 is undefined
        warn(f"{label}: a finger's tip is not below its base; the estimate expects a frame of the open "
             f"gripper, fingers hanging down the image")
    else:
        closure = [getattr(profile.fingers[side], "theta_entire", float("nan")) for side in ("left", "right")] \
            if hasattr(profile, "fingers") else []
        if closure and all(abs(b) > CLOSED_FRACTION * c and abs(b) > OPEN_BEND_WARN for b, c in zip(bends, closure)):
            raise FrameSceneError(
                f"{label}: the fingers are bent by {bends[0]:.2f} and {bends[1]:.2f} rad (eq. 4), more than "
                f"{CLOSED_FRACTION:g} of the profile's full closure ({closure[0]:.2f}, {closure[1]:.2f} rad): this is a "
                f"frame of the closed gripper; estimate and score predict the closure from a frame of the open "
                f"gripper, taken before it closes")
        if max(abs(b) for b in bends) > OPEN_BEND_WARN:
            warn(f"{label}: the fingers look bent ({bends[0]:.2f} and {bends[1]:.2f} rad by eq. 4); the "
                 f"estimate expects a frame of the open gripper before it closes")
    return Scene(path=label, frame=loaded, segmentation=seg, camera=camera, keypoints=keypoints,
                 bases_mm=bases, pose=pose, sdf=sdf, gripper=gripper)
