"""Accuracy of the vision front end on rendered noisy scenes, and speed of the segmentation backends.

Run from the repository root:

    .venv/bin/python benchmarks/vision_accuracy.py              # 20 scenes (about half a minute)
    .venv/bin/python benchmarks/vision_accuracy.py --scenes 40
    .venv/bin/python benchmarks/vision_accuracy.py --variants 6  # the renderer variants' table
    .venv/bin/python benchmarks/vision_accuracy.py --plane 6     # plane depth on round fingers (issue 31)
    .venv/bin/python benchmarks/vision_accuracy.py --distortion 4  # lenses undone and ignored (issue 32)
    .venv/bin/python benchmarks/vision_accuracy.py --theta         # Theta read back across Theta (issue 43)

and paste the printed markdown into benchmarks/RESULTS.md. Each scene is a gripper (L = 52 mm,
r = 4 mm) rendered twice with colour and depth noise and depth holes, with ground truth from the
renderer's geometry: open with an object between the fingers (base, tip, L by eq. 5, the object's
signed-distance grid) and closed along the free arc of Theta with no object (base, tip, Theta by
eq. 4, the paper's observed positions). Every frame goes through the whole pipeline: ``segment``,
``PlaneCamera.from_frame``, ``gripper_keypoints``, ``object_sdf``.

The renderer variants (:data:`VARIANTS`: flat-cut bases, a body in view, round fingers, object
faces +-3 mm, touching tips, a tilted camera, anti-aliasing, lighting and noise, all at once) go
through the public one-frame calibration (``softgrip_calib.one_frame.one_frame_from_frames``) and the
measured object outline (:func:`variant_errors`), compared with the renderer's geometry against the
issue's goals (:data:`VARIANT_GOALS`).

The plane sweep (:func:`plane_errors`, ``--plane``) renders round and flat fingers with depth noise,
holes and the depth image smoothed across the fingers' outlines as a depth sensor does
(:data:`PLANE_BLURS_PX`), and reports the relief and plane depth each frame measured, the one-frame
calibration's errors, and the paper's geometric estimate without an object (from the open frame)
against the observed closed fingers.

The lens sweep (:func:`distortion_table`, ``--distortion``) renders the default variant through each
of :data:`LENSES` (the renderer's ``Scene.distortion``) and compares the one-frame calibration (against
the truth) and the geometric estimate with the object (against the same scene's pinhole rendering),
with the distortion undone by the pipeline and ignored (the intrinsics' model set to none).

The scene sets, :func:`measure` and :func:`variant_errors` are also what ``tests/vision`` asserts on.
"""

from __future__ import annotations

import argparse
import functools
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softgrip_jax import Geometric, SDFGrid
from softgrip_vision.coverage import edge_coverage
from softgrip_vision.frames import Frame
from softgrip_vision.geometry import PlaneCamera
from softgrip_vision.keypoints import gripper_keypoints, resample_polyline
from softgrip_vision.object_sdf import object_sdf
from softgrip_vision.segmentation import segment, segment_batch
_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:  # the test support `synthetic` sits at the root of the checkout
    sys.path.insert(0, _ROOT)
from synthetic.render import LABEL_FIRST_FINGER, Scene, d405_intrinsics, mm_to_px, project, render, render_labels  # noqa: E402
from synthetic.rod import free_arc_points  # noqa: E402
from synthetic.scenes import gripper_centrelines  # noqa: E402
from synthetic.shapes import SHAPES, shape  # noqa: E402

LENGTH_MM = 52.0
HALF_THICKNESS_MM = 4.0
N_LINKS = 10
INTRINSICS = d405_intrinsics()  # 640 x 480
OBJECTS: tuple[str | None, ...] = (*SHAPES, None)

REQUIREMENTS = {  # the bounds, asserted by tests/vision
    "base_px": 1.5, "tip_px": 1.5, "theta_rad": 0.01, "length_pct": 1.0, "sdf_zero_level_px": 1.0,
}


@dataclass(frozen=True)
class AccuracyScene:
    """One gripper pose, object and noise draw; lengths in mm in the gripper plane.

    Attributes:
        index: position in the set (also the seed of the noise).
        theta: entire bending angle of both fingers, rad.
        center_mm: (x, y) of the gripper centre between the finger bases.
        base_separation_mm: distance between the finger bases (wide enough for the closed fingers
            to stay apart and the open ones to clear the object).
        plane_depth_mm: camera-to-gripper-plane distance.
        object_name: a key of ``SHAPES``, or None for no object.
        object_size_mm, object_angle: the object's bounding-circle diameter and rotation (rad).
        object_center_mm: (x, y) of its centroid.
        color_noise_sigma: colour noise (levels).
        n_depth_holes: zero-depth blobs per frame.
    """

    index: int
    theta: float
    center_mm: tuple[float, float]
    base_separation_mm: float
    plane_depth_mm: float
    object_name: str | None
    object_size_mm: float
    object_angle: float
    object_center_mm: tuple[float, float]
    color_noise_sigma: float
    n_depth_holes: int

    def arc_offsets(self, arc_lengths: np.ndarray) -> np.ndarray:
        """(K, 2) points of the closed (free) left finger at the given arc lengths, from its base."""
        return np.asarray(free_arc_points((0.0, 0.0), self.theta, LENGTH_MM, arc_lengths))

    def centrelines(self, closed: bool) -> list[np.ndarray]:
        """[left, right] finger centrelines (K, 2) in mm, base first."""
        shape_ = self.arc_offsets(np.linspace(0.0, LENGTH_MM, 257)) if closed else None
        return gripper_centrelines(self.center_mm, self.base_separation_mm, LENGTH_MM, 64,
                                   left_shape=shape_, right_shape=shape_)

    def object_polygon(self) -> np.ndarray | None:
        """(V, 2) the object's outline in mm, or None."""
        if self.object_name is None:
            return None
        return shape(self.object_name, self.object_size_mm, self.object_angle) + self.object_center_mm

    def scene(self, closed: bool) -> Scene:
        """The open frame (with the object) or the closed one (without: the calibration frame)."""
        return Scene(self.centrelines(closed), half_thickness=HALF_THICKNESS_MM,
                     object_polygon=None if closed else self.object_polygon(),
                     plane_depth_mm=self.plane_depth_mm, color_noise_sigma=self.color_noise_sigma,
                     n_depth_holes=self.n_depth_holes, seed=2 * self.index + int(closed))


def accuracy_scenes(n: int = 20) -> list[AccuracyScene]:
    """``n`` scenes: Theta spread evenly over [0.3, 0.8], objects cycling through every shape and
    "none", positions, depths and noise drawn from the scene's index."""
    scenes = []
    for i in range(n):
        rng = np.random.default_rng(1000 + i)
        theta = 0.3 + 0.5 * (i + rng.uniform()) / n
        size = rng.uniform(20.0, 32.0)
        offset = rng.uniform(-4.0, 4.0)
        tip_x = LENGTH_MM * math.sin(theta) ** 2 / theta  # closed tip's offset from its base
        separation = max(2.0 * tip_x + 2.0 * HALF_THICKNESS_MM + 8.0,
                         size + 2.0 * abs(offset) + 2.0 * HALF_THICKNESS_MM + 8.0)
        center = (rng.uniform(-10.0, 10.0), rng.uniform(-50.0, -40.0))
        scenes.append(AccuracyScene(
            index=i, theta=float(theta), center_mm=center, base_separation_mm=float(separation),
            plane_depth_mm=float(rng.uniform(110.0, 130.0)), object_name=OBJECTS[i % len(OBJECTS)],
            object_size_mm=float(size), object_angle=float(rng.uniform(0.0, 2.0 * math.pi)),
            object_center_mm=(center[0] + offset, center[1] + rng.uniform(0.45, 0.7) * LENGTH_MM),
            color_noise_sigma=float(rng.uniform(2.0, 5.0)), n_depth_holes=int(rng.integers(3, 10)),
        ))
    return scenes


@dataclass(frozen=True)
class SceneErrors:
    """Worst errors of one scene (over both fingers; base and tip over both frames).

    Attributes:
        base_px, tip_px: distance of the estimated base / tip from the true one, px.
        theta_rad: |Theta (eq. 4, closed frame) - true Theta|.
        length_pct: |L (eq. 5, open frame) - true L| / true L, percent.
        observed_px: largest distance of the N = 10 observed positions (closed frame) from the true
            arc's points at the same arc lengths, px.
        half_thickness_mm: |estimated r - true r|.
        sdf_zero_level_px: largest distance from the grid's zero level (crossings between grid
            points) to the true outline, px; None without object.
        sdf_outline_px: largest |SDF| on the true outline, px, except within 2 px of the apex of a
            corner sharper than 100 degrees; None without object.
        sdf_apex_px: largest |SDF| on the whole true outline, px: at sharp apexes, which no pixel
            centre may sample, the mask (and so the zero level) falls short; None without object.
        fingers_found: fingers (of 4: two per frame) segmented and matching the true finger
            (intersection over union >= 0.9).
    """

    base_px: float
    tip_px: float
    theta_rad: float
    length_pct: float
    observed_px: float
    half_thickness_mm: float
    sdf_zero_level_px: float | None
    sdf_outline_px: float | None
    sdf_apex_px: float | None
    fingers_found: int


@functools.cache
def measure(scene: AccuracyScene) -> SceneErrors:
    """Run the pipeline on the scene's open and closed frames and compare with the ground truth.

    A segmentation or keypoint error is not caught: it fails the run (and the tests) loudly.
    """
    errors: dict[str, list[float]] = {"base": [], "tip": [], "theta": [], "length": [], "observed": [],
                                      "thickness": []}
    found = 0
    sdf_metrics: tuple[float, float, float] | None = None
    to_px = functools.partial(mm_to_px, intrinsics=INTRINSICS, depth_mm=scene.plane_depth_mm)
    for closed in (False, True):
        scene_ = scene.scene(closed)
        frame = render(scene_, INTRINSICS)
        labels = render_labels(scene_, INTRINSICS)
        seg = segment(frame)
        camera = PlaneCamera.from_frame(frame, seg.fingers)
        for k, (finger, true_line) in enumerate(zip(gripper_keypoints(seg, camera), scene_.fingers)):
            truth = labels == LABEL_FIRST_FINGER + k
            mask = seg.left_finger if k == 0 else seg.right_finger
            found += bool((mask & truth).sum() >= 0.9 * (mask | truth).sum())
            errors["base"].append(float(np.hypot(*(finger.base_px - to_px(true_line[0])))))
            errors["tip"].append(float(np.hypot(*(finger.tip_px - to_px(true_line[-1])))))
            errors["thickness"].append(abs(finger.half_thickness_mm - HALF_THICKNESS_MM))
            if closed:
                errors["theta"].append(abs(finger.theta - scene.theta))
                true_obs = true_line[0] + scene.arc_offsets(np.arange(N_LINKS + 1) * LENGTH_MM / N_LINKS) \
                    * (1.0 if k == 0 else -1.0, 1.0)
                errors["observed"].append(float(np.hypot(*(finger.observed_px(N_LINKS) - to_px(true_obs)).T).max()))
            else:
                errors["length"].append(100.0 * abs(finger.length_mm - LENGTH_MM) / LENGTH_MM)
        if not closed and scene.object_name is not None:
            true_outline_px = mm_to_px(scene.object_polygon(), INTRINSICS, scene.plane_depth_mm)
            grid = object_sdf(seg.object, camera, coverage=edge_coverage(frame.color, seg.object))
            sdf_metrics = _sdf_errors(grid, camera, true_outline_px)
    return SceneErrors(
        base_px=max(errors["base"]), tip_px=max(errors["tip"]), theta_rad=max(errors["theta"]),
        length_pct=max(errors["length"]), observed_px=max(errors["observed"]),
        half_thickness_mm=max(errors["thickness"]),
        sdf_zero_level_px=None if sdf_metrics is None else sdf_metrics[0],
        sdf_outline_px=None if sdf_metrics is None else sdf_metrics[1],
        sdf_apex_px=None if sdf_metrics is None else sdf_metrics[2],
        fingers_found=found,
    )


def zero_level_px(values: np.ndarray) -> np.ndarray:
    """(P, 2) points (u, v) where bilinear interpolation of a grid (H, W) crosses zero along its rows
    and columns (linear between each pair of neighbours of opposite sign)."""
    points = []
    for axis in (1, 0):
        a = np.take(values, np.arange(values.shape[axis] - 1), axis=axis)
        b = np.take(values, np.arange(1, values.shape[axis]), axis=axis)
        v, u = np.nonzero((a < 0) != (b < 0))
        step = a[v, u] / (a[v, u] - b[v, u])
        points.append(np.column_stack([u + step, v]) if axis == 1 else np.column_stack([u, v + step]))
    return np.vstack(points)


def distance_to_outline(points: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """(P,) unsigned distance from points (P, 2) to a closed polygon (V, 2), in their unit."""
    a = outline[None]
    ab = np.roll(outline, -1, axis=0)[None] - a
    ap = points[:, None] - a
    t = np.clip((ap * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.hypot(*(ap - t[..., None] * ab).transpose(2, 0, 1)).min(axis=1)


@jax.jit
def sdf_lookup(grid: SDFGrid, points_mm: jax.Array) -> jax.Array:
    """Jitted ``grid.distance(points_mm)``: one compilation per points shape, not one per operation."""
    return grid.distance(points_mm)


def sharp_vertices(outline: np.ndarray, max_angle_deg: float = 100.0) -> np.ndarray:
    """(S, 2) the vertices of a closed polygon (V, 2) whose interior angle is below max_angle_deg
    (on either side: a sharp notch is as hard to sample as a sharp tip)."""
    before = np.roll(outline, 1, axis=0) - outline
    after = np.roll(outline, -1, axis=0) - outline
    cosine = (before * after).sum(1) / (np.hypot(*before.T) * np.hypot(*after.T))
    return outline[np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) < max_angle_deg]


def _sdf_errors(grid: SDFGrid, camera: PlaneCamera, outline_px: np.ndarray) -> tuple[float, float, float]:
    """Worst distances in px: zero level -> outline; outline -> zero level away from sharp apexes,
    and everywhere."""
    zero_level = float(distance_to_outline(zero_level_px(np.asarray(grid.values)), outline_px).max())
    samples = resample_polyline(np.vstack([outline_px, outline_px[:1]]), 4096)  # one compilation
    at_outline = np.abs(np.asarray(sdf_lookup(grid, jnp.asarray(camera.px_to_mm(samples))))) / camera.mm_per_px
    apexes = sharp_vertices(outline_px)
    if len(apexes):
        near_apex = np.hypot(*(samples[:, None] - apexes[None]).transpose(2, 0, 1)).min(axis=1) < 2.0
    else:
        near_apex = np.zeros(len(samples), bool)
    return zero_level, float(at_outline[~near_apex].max()), float(at_outline.max())


# ---------------------------------------------------------------------------------------------
# Renderer variants: what real set-ups have that the default synthetic frame does not


#: Each variant's changes to the rendered scene (``synthetic.render.Scene`` fields), plus
#: ``"touching"``: the closed frame's fingertips overlap by that many mm (the bases moved together).
VARIANTS: dict[str, dict] = {
    "default": {},
    "flat base": {"base_end": "flat"},
    "flat base, body in view": {"base_end": "flat", "palm": True, "palm_height_mm": 20.0},
    "round fingers": {"finger_section": "round"},
    "round fingers, flat base": {"finger_section": "round", "base_end": "flat"},
    "round fingers, depth blur 1.7 px": {"finger_section": "round", "depth_blur_px": 1.7},
    "object face -3 mm": {"object_depth_offset_mm": -3.0},
    "object face +3 mm": {"object_depth_offset_mm": 3.0},
    "tips touching": {"touching": 0.3},
    "tilt 5 deg": {"tilt_deg": (4.0, -3.0)},
    "tilt 10 deg": {"tilt_deg": (7.0, 7.0)},
    "anti-aliased": {"supersample": 4},
    "lighting and noise": {"light_gain": 0.8, "light_gradient": 0.3, "color_noise_sigma": 6.0,
                           "depth_noise_sigma_mm": 0.6, "n_depth_holes": 12},
    "all together": {"finger_section": "round", "base_end": "flat", "palm": True, "palm_height_mm": 20.0,
                     "object_depth_offset_mm": -3.0,
                     "touching": 0.3, "tilt_deg": (5.0, 4.0), "supersample": 3, "light_gradient": 0.3},
}

#: The issue's goals for each variant (mm, rad, percent).
VARIANT_GOALS = {"theta_rad": 0.01, "length_pct": 1.0, "separation_pct": 0.5, "half_thickness_mm": 0.3,
                 "sdf_mean_mm": 0.1, "closure_mid_mm": 0.3, "closure_tip_mm": 0.3}


@dataclass(frozen=True)
class VariantErrors:
    """One scene of one variant through one-frame calibration (both fingers' worst).

    Attributes:
        theta_rad: |Theta - truth| (eq. 4 on the closed frame).
        length_pct: |L - truth| / truth, percent (eq. 5 on the open frame).
        separation_pct: |W - truth| / truth, percent (the bases of the open frame).
        half_thickness_mm: |r - truth|.
        sdf_mean_mm: mean |SDF| on the true outline of the object (its face), mm.
        closure_mid_mm, closure_tip_mm: distance between the calibrated model's closure without an
            object and the true one, at joint N/2 and N (from the base, along the gripper's axes).
        detected: what the measurement detected in the open frame (profile ``vision.detected``).
    """

    theta_rad: float
    length_pct: float
    separation_pct: float
    half_thickness_mm: float
    sdf_mean_mm: float
    closure_mid_mm: float
    closure_tip_mm: float
    detected: dict


def variant_scenes(scene: AccuracyScene, variant: str) -> tuple[Scene, Scene]:
    """(open frame with the object, closed frame without) of a scene rendered as ``variant``."""
    changes = dict(VARIANTS[variant])
    overlap = changes.pop("touching", None)
    separation = scene.base_separation_mm
    polygon = scene.object_polygon()
    if overlap is not None:
        tip_x = float(scene.arc_offsets(np.array([LENGTH_MM]))[0, 0])
        separation = 2.0 * (tip_x + HALF_THICKNESS_MM) - overlap
        room = separation - 2.0 * HALF_THICKNESS_MM - 6.0  # the object still fits between the open fingers
        centroid = polygon.mean(axis=0)
        size = 2.0 * np.hypot(*(polygon - centroid).T).max()
        if size > room:
            polygon = centroid + (polygon - centroid) * room / size
        polygon = polygon + (scene.center_mm[0] - centroid[0], 0.0)
    arc = scene.arc_offsets(np.linspace(0.0, LENGTH_MM, 257))
    common = dict(half_thickness=HALF_THICKNESS_MM, plane_depth_mm=scene.plane_depth_mm,
                  color_noise_sigma=scene.color_noise_sigma, n_depth_holes=scene.n_depth_holes)
    common.update(changes)
    opened = Scene(gripper_centrelines(scene.center_mm, separation, LENGTH_MM, 64), object_polygon=polygon,
                   seed=2 * scene.index, **common)
    closed = Scene(gripper_centrelines(scene.center_mm, separation, LENGTH_MM, 64, left_shape=arc, right_shape=arc),
                   seed=2 * scene.index + 1, **common)
    return opened, closed


def profile_errors(profile, scene) -> dict[str, list[float]]:
    """Each finger's calibration errors against the renderer's truth: Theta (rad), L (%), r (mm),
    and the free closure's mid-finger and tip joints (mm), as lists [left, right]."""
    from softgrip_calib.one_frame import free_closure_joints
    from softgrip_calib.profile import FingerEntry

    truth = FingerEntry(LENGTH_MM, scene.theta, HALF_THICKNESS_MM, N_LINKS)
    errors: dict[str, list[float]] = {"theta": [], "length": [], "r": [], "mid": [], "tip": []}
    for side in ("left", "right"):
        entry = profile.fingers[side]
        errors["theta"].append(abs(entry.theta_entire - scene.theta))
        errors["length"].append(100.0 * abs(entry.length - LENGTH_MM) / LENGTH_MM)
        errors["r"].append(abs(entry.half_thickness - HALF_THICKNESS_MM))
        gap = np.hypot(*(free_closure_joints(entry, np.zeros(2), side) - free_closure_joints(truth, np.zeros(2), side)).T)
        errors["mid"].append(float(gap[N_LINKS // 2]))
        errors["tip"].append(float(gap[N_LINKS]))
    return errors


def variant_errors(scene: AccuracyScene, variant: str) -> VariantErrors:
    """Render the scene as ``variant``, calibrate from it (one frame) and compare with the truth.

    A segmentation or keypoint error is not caught: it fails the run (and the tests) loudly.
    """
    from softgrip_calib.one_frame import frame_measurement, one_frame_from_frames

    opened, closed = variant_scenes(scene, variant)
    open_frame, closed_frame = render(opened, INTRINSICS), render(closed, INTRINSICS)
    profile = one_frame_from_frames(closed_frame, open_frame, N_LINKS)
    separation = float(np.hypot(*(opened.fingers[1][0] - opened.fingers[0][0])))
    errors = profile_errors(profile, scene)
    measured = frame_measurement(open_frame)
    outline = opened.object_polygon
    samples = resample_polyline(np.vstack([outline, outline[:1]]), 4096)
    seen_px = project(opened, samples, INTRINSICS, opened.object_depth_offset_mm)
    grid = measured.object_sdf(open_frame)
    sdf = np.asarray(sdf_lookup(grid, jnp.asarray(measured.object_camera.px_to_mm(seen_px), jnp.float32)))
    return VariantErrors(
        theta_rad=max(errors["theta"]), length_pct=max(errors["length"]),
        separation_pct=100.0 * abs(profile.base_separation - separation) / separation,
        half_thickness_mm=max(errors["r"]), sdf_mean_mm=float(np.abs(sdf).mean()),
        closure_mid_mm=max(errors["mid"]), closure_tip_mm=max(errors["tip"]),
        detected=profile.vision.get("detected", {}).get("open", {}),
    )


def variant_table(n_scenes: int) -> list[str]:
    """Markdown rows: per variant, the worst of each error over ``n_scenes`` scenes."""
    scenes = [s for s in accuracy_scenes(4 * n_scenes) if s.object_name is not None][:n_scenes]
    fields = list(VARIANT_GOALS)
    lines = ["| variant | " + " | ".join(fields) + " |", "| --- " * (len(fields) + 1) + "|",
             "| goal | " + " | ".join(f"{VARIANT_GOALS[f]:g}" for f in fields) + " |"]
    for variant in VARIANTS:
        results = [variant_errors(scene, variant) for scene in scenes]
        cells = []
        for f in fields:
            worst = max(getattr(r, f) for r in results)
            cells.append(f"{worst:.3f}" + ("" if worst <= VARIANT_GOALS[f] else " (over)"))
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    return lines


# ---------------------------------------------------------------------------------------------
# Plane depth on round fingers (issue 31): the depth image smoothed across the fingers' outlines


#: Standard deviations (px) of the Gaussian smoothing of the depth image swept: sharp, about a
#: 5 x 5 filter, about a 9 x 9 one (what a real camera's frames looked like), and beyond.
PLANE_BLURS_PX: tuple[float, ...] = (0.0, 1.1, 1.7, 2.5)
#: The issue's goals (rad, percent, percent, mm); the plane is not a goal in itself.
PLANE_GOALS = {"theta_rad": 0.01, "length_pct": 1.0, "separation_pct": 0.5, "closure_mm": 0.3}


@dataclass(frozen=True)
class PlaneErrors:
    """One scene through one-frame calibration and the geometric estimate without an object.

    Attributes:
        relief_mm: (open, closed) the relief each frame measured (mean of its two fingers), mm.
        plane_mm: (open, closed) each frame's plane depth at the gripper minus the truth, mm.
        theta_rad, length_pct, separation_pct: as :class:`VariantErrors` (worst finger).
        closure_mm: largest distance, over both fingers and every joint, between the paper's
            geometric estimate on the open frame (no object: case (a), from the bases it detects)
            and the observed closed fingers (the closed frame's true centrelines at N equal arc
            lengths), mm.
        disagreement_warned: the calibration warned that the two planes disagree.
    """

    relief_mm: tuple[float, float]
    plane_mm: tuple[float, float]
    theta_rad: float
    length_pct: float
    separation_pct: float
    closure_mm: float
    disagreement_warned: bool


def plane_scenes(scene: AccuracyScene, section: str, blur_px: float, *,
                 closed_depth_shift_mm: float = 0.0) -> tuple[Scene, Scene]:
    """(open, closed) frames of ``scene`` without an object: fingers of ``section``, 0.3 mm depth
    noise, the scene's depth holes, the depth smoothed by ``blur_px``; the closed frame's gripper
    ``closed_depth_shift_mm`` farther from the camera (0: the same pose, as calibration expects)."""
    common = dict(half_thickness=HALF_THICKNESS_MM, color_noise_sigma=scene.color_noise_sigma,
                  n_depth_holes=scene.n_depth_holes, depth_noise_sigma_mm=0.3, finger_section=section,
                  depth_blur_px=blur_px)
    arc = scene.arc_offsets(np.linspace(0.0, LENGTH_MM, 257))
    opened = Scene(gripper_centrelines(scene.center_mm, scene.base_separation_mm, LENGTH_MM, 64),
                   plane_depth_mm=scene.plane_depth_mm, seed=2 * scene.index, **common)
    closed = Scene(gripper_centrelines(scene.center_mm, scene.base_separation_mm, LENGTH_MM, 64,
                                       left_shape=arc, right_shape=arc),
                   plane_depth_mm=scene.plane_depth_mm + closed_depth_shift_mm, seed=2 * scene.index + 1, **common)
    return opened, closed


def plane_errors(scene: AccuracyScene, section: str = "round", blur_px: float = 0.0) -> PlaneErrors:
    """Calibrate from :func:`plane_scenes` (one frame pair) and estimate the closure without an
    object from the open frame with the paper's geometric method; compare with the truth."""
    import warnings

    from softgrip_calib.one_frame import one_frame_from_frames
    from softgrip_vision.measure import MeasurementWarning
    from softgrip_vision.scene import frame_scene

    opened, closed = plane_scenes(scene, section, blur_px)
    open_frame, closed_frame = render(opened, INTRINSICS), render(closed, INTRINSICS)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        profile = one_frame_from_frames(closed_frame, open_frame, N_LINKS)
    warned = any(issubclass(w.category, MeasurementWarning) and "gripper plane is" in str(w.message) for w in caught)
    detected = profile.vision["detected"]
    # Without the record (a checkout before it, for comparison), each frame's plane on the optical
    # axis: the same depth for these untilted scenes.
    depths = profile.vision.get("plane_depth_mm") or {f: detected[f]["plane"]["depth_mm"] for f in ("open", "closed")}
    relief = tuple(float(np.mean(list(detected[f]["finger_relief_mm"].values()))) for f in ("open", "closed"))
    separation = float(np.hypot(*(opened.fingers[1][0] - opened.fingers[0][0])))
    theta = max(abs(profile.fingers[side].theta_entire - scene.theta) for side in ("left", "right"))
    length = max(100.0 * abs(profile.fingers[side].length - LENGTH_MM) / LENGTH_MM for side in ("left", "right"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grasp = frame_scene(open_frame, profile).estimate(estimator=Geometric())
    arcs = np.arange(N_LINKS + 1) * LENGTH_MM / N_LINKS
    closure = 0.0
    for k, (estimate, line) in enumerate(zip((grasp.left, grasp.right), closed.fingers)):
        observed = line[0] + scene.arc_offsets(arcs) * (1.0 if k == 0 else -1.0, 1.0)
        closure = max(closure, float(np.hypot(*(np.asarray(estimate.joints) - observed).T).max()))
    return PlaneErrors(
        relief_mm=relief, plane_mm=(depths["open"] - scene.plane_depth_mm, depths["closed"] - scene.plane_depth_mm),
        theta_rad=theta, length_pct=length,
        separation_pct=100.0 * abs(profile.base_separation - separation) / separation,
        closure_mm=closure, disagreement_warned=warned)


def plane_table(n_scenes: int) -> list[str]:
    """Markdown rows: per finger section and depth smoothing, the range of the relief and plane
    errors and the worst of each calibration error over ``n_scenes`` scenes."""
    from softgrip_jax import SoftgripError

    scenes = accuracy_scenes(n_scenes)
    lines = ["| section | depth blur (px) | relief open (mm) | relief closed (mm) | plane open - truth (mm) "
             "| plane closed - truth (mm) | theta_rad | length_pct | separation_pct | closure_mm | plane warnings "
             "| failed |",
             "| --- " * 12 + "|",
             "| goal | | r = 4 (round), 0 (flat) | | | | " + " | ".join(f"{g:g}" for g in PLANE_GOALS.values())
             + " | none | none |"]
    for section in ("round", "flat"):
        for blur in PLANE_BLURS_PX:
            results, failed = [], 0
            for scene in scenes:
                try:
                    results.append(plane_errors(scene, section, blur))
                except SoftgripError:  # the calibration refused the frames: counted, not fatal
                    failed += 1
            if not results:
                lines.append(f"| {section} | {blur:g} | " + " | ".join(["-"] * 9) + f" | {failed}/{len(scenes)} |")
                continue

            def span(values: list[float]) -> str:
                return f"{min(values):+.2f} .. {max(values):+.2f}"

            cells = [span([r.relief_mm[0] for r in results]).replace("+", ""),
                     span([r.relief_mm[1] for r in results]).replace("+", ""),
                     span([r.plane_mm[0] for r in results]), span([r.plane_mm[1] for r in results])]
            for name, goal in PLANE_GOALS.items():
                worst = max(getattr(r, name) for r in results)
                cells.append(f"{worst:.3f}" + ("" if worst <= goal else " (over)"))
            cells.append(f"{sum(r.disagreement_warned for r in results)}/{len(results)}")
            cells.append(f"{failed}/{len(scenes)}")
            lines.append(f"| {section} | {blur:g} | " + " | ".join(cells) + " |")
    return lines


# ---------------------------------------------------------------------------------------------
# Lens distortion (issue 32): rendered through a lens, undistorted by the pipeline


#: Lenses swept by ``--distortion`` (OpenCV's coefficient order; none of them folds back over a
#: 640x480 D405 image): barrel, strong barrel held monotonic by k2, pincushion, decentring (tangential),
#: and an equidistant fisheye (Kannala-Brandt) of mild coefficients.
LENSES: dict[str, tuple[str, tuple[float, ...]]] = {
    "barrel k1 -0.1": ("brown_conrady", (-0.1, 0.0, 0.0, 0.0, 0.0)),
    "barrel k1 -0.3, k2 0.1": ("brown_conrady", (-0.3, 0.1, 0.0, 0.0, 0.0)),
    "pincushion k1 +0.1": ("brown_conrady", (0.1, 0.0, 0.0, 0.0, 0.0)),
    "tangential p1 = p2 = 0.005": ("brown_conrady", (0.0, 0.0, 0.005, 0.005, 0.0)),
    "fisheye k1 0.05, k2 -0.01": ("kannala_brandt4", (0.05, -0.01, 0.0, 0.0)),
}


def lens_errors(scene: AccuracyScene, lens: tuple[str, tuple[float, ...]] | None,
                corrected: bool = True) -> tuple[VariantErrors, np.ndarray]:
    """One-frame calibration and the geometric estimate (with the object) on ``scene`` rendered
    through ``lens`` (None: pinhole). ``corrected=False`` drops the lens from the frames' intrinsics
    (model "none", the same K) before the pipeline sees them: what happens when distortion is
    ignored. Returns (the calibration's :class:`VariantErrors` against the truth, without
    ``sdf_mean_mm`` (NaN) and ``detected``; the estimate's joints (2, N+1, 2), mm)."""
    import dataclasses
    import warnings

    from softgrip_calib.one_frame import one_frame_from_frames
    from softgrip_vision.scene import frame_scene

    opened, closed = variant_scenes(scene, "default")
    if lens is not None:
        opened, closed = (dataclasses.replace(s, distortion=lens) for s in (opened, closed))
    frames = [render(s, INTRINSICS) for s in (opened, closed)]
    if not corrected:
        frames = [Frame(f.color, f.depth, dataclasses.replace(f.intrinsics, model="none", coeffs=()))
                  for f in frames]
    open_frame, closed_frame = frames
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        profile = one_frame_from_frames(closed_frame, open_frame, N_LINKS)
        grasp = frame_scene(open_frame, profile).estimate(estimator=Geometric())
    separation = float(np.hypot(*(opened.fingers[1][0] - opened.fingers[0][0])))
    errors = profile_errors(profile, scene)
    result = VariantErrors(
        theta_rad=max(errors["theta"]), length_pct=max(errors["length"]),
        separation_pct=100.0 * abs(profile.base_separation - separation) / separation,
        half_thickness_mm=max(errors["r"]), sdf_mean_mm=float("nan"),
        closure_mid_mm=max(errors["mid"]), closure_tip_mm=max(errors["tip"]), detected={})
    return result, np.stack([np.asarray(grasp.left.joints), np.asarray(grasp.right.joints)])


def lens_shift_px(lens: tuple[str, tuple[float, ...]]) -> float:
    """The largest distance (px) between where ``lens`` images a pixel of the 640x480 pinhole image
    and where the pinhole camera does, over the pixels the lens still sees."""
    import dataclasses

    from softgrip_vision.frames import distort_points

    intr = dataclasses.replace(INTRINSICS, model=lens[0], coeffs=lens[1])
    v, u = np.mgrid[0:INTRINSICS.height:8, 0:INTRINSICS.width:8].astype(np.float64)
    ideal = np.stack([u, v], axis=-1).reshape(-1, 2)
    seen = distort_points(intr, ideal)
    inside = (seen >= -0.5).all(axis=1) & (seen[:, 0] < INTRINSICS.width - 0.5) & (seen[:, 1] < INTRINSICS.height - 0.5)
    return float(np.hypot(*(seen - ideal)[inside].T).max())


#: The columns of the ``--distortion`` table and their goals (as :data:`VARIANT_GOALS`); estimate_mm:
#: the geometric estimate with the object against the pinhole frames' (0.3 mm, as the closure).
LENS_GOALS = {"theta_rad": 0.01, "length_pct": 1.0, "separation_pct": 0.5, "closure_tip_mm": 0.3, "estimate_mm": 0.3}


def distortion_table(n_scenes: int) -> list[str]:
    """Markdown rows: per lens, corrected and not, the worst calibration errors against the truth,
    and the estimate against the pinhole rendering's, over ``n_scenes`` scenes with an object."""
    from softgrip_jax import SoftgripError

    scenes = [s for s in accuracy_scenes(4 * n_scenes) if s.object_name is not None][:n_scenes]
    references = {s.index: lens_errors(s, None) for s in scenes}
    lines = ["| lens | largest shift (px) | distortion | " + " | ".join(LENS_GOALS) + " | failed |",
             "| --- " * (len(LENS_GOALS) + 4) + "|",
             "| goal | | | " + " | ".join(f"{g:g}" for g in LENS_GOALS.values()) + " | none |"]

    def row(name: str, shift: str, how: str, results: list[tuple[VariantErrors, float]], failed: int) -> str:
        cells = []
        for field, goal in LENS_GOALS.items():
            if not results:
                cells.append("-")
                continue
            worst = max(e if field == "estimate_mm" else getattr(r, field) for r, e in results)
            cells.append(f"{worst:.3f}" + ("" if worst <= goal else " (over)"))
        return f"| {name} | {shift} | {how} | " + " | ".join(cells) + f" | {failed}/{len(scenes)} |"

    lines.append(row("none (pinhole)", "0", "-", [(r, 0.0) for r, _ in references.values()], 0))
    for name, lens in LENSES.items():
        for corrected in (True, False):
            results, failed = [], 0
            for s in scenes:
                try:
                    errors, joints = lens_errors(s, lens, corrected)
                except SoftgripError:  # the pipeline refused the frames: counted, not fatal
                    failed += 1
                    continue
                results.append((errors, float(np.hypot(*(joints - references[s.index][1]).reshape(-1, 2).T).max())))
            lines.append(row(name, f"{lens_shift_px(lens):.1f}", "undone" if corrected else "ignored",
                             results, failed))
    return lines


def time_backends(frames: list[Frame], repeats: int = 3) -> dict[str, float]:
    """Best-of-``repeats`` seconds to segment ``frames`` with each backend (after one warm-up)."""
    seconds = {}
    for backend in ("opencv", "kornia"):
        segment_batch(frames, backend=backend)
        runs = []
        for _ in range(repeats):
            start = time.perf_counter()
            segment_batch(frames, backend=backend)
            runs.append(time.perf_counter() - start)
        seconds[backend] = min(runs)
    return seconds


def backend_disagreement(frames: list[Frame]) -> float:
    """Largest fraction of pixels on which the two backends' gripper or object masks differ."""
    worst = 0.0
    for a, b in zip(segment_batch(frames, backend="opencv"), segment_batch(frames, backend="kornia")):
        for name in ("gripper", "left_finger", "right_finger", "object"):
            worst = max(worst, float(np.mean(getattr(a, name) != getattr(b, name))))
    return worst


#: The Theta sweep (issue 43): closed frames of fingers cut flat at the base, read back by eq. 4.
THETA_SWEEP = (0.4, 0.55, 0.65, 0.8)


def theta_table() -> list[str]:
    """Markdown rows: the signed error of Theta (one-frame calibration, mrad) per true Theta, over both
    fingers of six scenes each: flat base ends, round and flat sections, the gripper 25 mm left,
    centred and 25 mm right (about 80 px), anti-aliased edges (supersample 3)."""
    import itertools
    import warnings

    from softgrip_calib.one_frame import one_frame_from_frames

    lines = ["| Theta (rad) | mean error (mrad) | smallest | largest | fingers |", "|---|---|---|---|---|"]
    for theta in THETA_SWEEP:
        arc = np.asarray(free_arc_points((0.0, 0.0), theta, LENGTH_MM, np.linspace(0.0, LENGTH_MM, 257)))
        errors = []
        for centre_x, section in itertools.product((-25.0, 0.0, 25.0), ("round", "flat")):
            centre = np.array([centre_x, -40.0])
            common = dict(half_thickness=HALF_THICKNESS_MM, plane_depth_mm=120.0, base_end="flat",
                          finger_section=section, supersample=3)
            opened = Scene(gripper_centrelines(centre, 76.0, LENGTH_MM, 64), seed=1, **common)
            closed = Scene(gripper_centrelines(centre, 76.0, LENGTH_MM, 64, left_shape=arc, right_shape=arc),
                           seed=2, **common)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                profile = one_frame_from_frames(render(closed, INTRINSICS), render(opened, INTRINSICS), N_LINKS)
            errors += [1e3 * (profile.fingers[side].theta_entire - theta) for side in ("left", "right")]
        lines.append(f"| {theta:g} | {np.mean(errors):+.2f} | {min(errors):+.2f} | {max(errors):+.2f} "
                     f"| {len(errors)} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=20, help="number of scenes (default 20)")
    parser.add_argument("--variants", type=int, metavar="SCENES",
                        help="instead, the renderer variants' table: one-frame calibration on SCENES scenes each")
    parser.add_argument("--plane", type=int, metavar="SCENES",
                        help="instead, the plane-depth sweep (issue 31): round and flat fingers, depth smoothing, "
                             "on SCENES scenes each")
    parser.add_argument("--distortion", type=int, metavar="SCENES",
                        help="instead, the lens sweep (issue 32): each of LENSES rendered, undone by the pipeline "
                             "and ignored, against the pinhole rendering, on SCENES scenes each")
    parser.add_argument("--theta", action="store_true",
                        help="instead, the Theta sweep (issue 43): Theta read back from flat-based closed frames")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _machine import describe

    if args.theta:
        print("Command: `.venv/bin/python benchmarks/vision_accuracy.py --theta`\n")
        print(f"Machine: {describe()}\n")
        print("\n".join(theta_table()))
        return

    if args.distortion:
        print(f"Command: `.venv/bin/python benchmarks/vision_accuracy.py --distortion {args.distortion}`\n")
        print(f"Machine: {describe()}\n")
        start = time.perf_counter()
        lines = distortion_table(args.distortion)
        print(f"#### Lens distortion: one-frame calibration and the geometric estimate on frames rendered through "
              f"a lens, the distortion undone by the pipeline or ignored (model none), worst of {args.distortion} "
              f"scenes per row ({time.perf_counter() - start:.0f} s)\n")
        print("\n".join(lines))
        return

    if args.plane:
        print(f"Command: `.venv/bin/python benchmarks/vision_accuracy.py --plane {args.plane}`\n")
        print(f"Machine: {describe()}\n")
        start = time.perf_counter()
        lines = plane_table(args.plane)
        print(f"#### Plane depth and one-frame calibration with the depth smoothed across the fingers' outlines, "
              f"worst of {args.plane} scenes per row ({time.perf_counter() - start:.0f} s)\n")
        print("\n".join(lines))
        return

    if args.variants:
        import warnings

        print(f"Command: `.venv/bin/python benchmarks/vision_accuracy.py --variants {args.variants}`\n")
        print(f"Machine: {describe()}\n")
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lines = variant_table(args.variants)
        print(f"### Renderer variants: one-frame calibration through the vision pipeline, worst of "
              f"{args.variants} scenes per variant ({time.perf_counter() - start:.0f} s)\n")
        print("\n".join(lines))
        return

    import cv2
    import kornia
    import torch

    print(f"Command: `.venv/bin/python benchmarks/vision_accuracy.py --scenes {args.scenes}`\n")
    print(f"Machine: {describe()}; OpenCV {cv2.__version__}, torch {torch.__version__}, "
          f"kornia {kornia.__version__}\n")
    start = time.perf_counter()
    scenes = accuracy_scenes(args.scenes)
    results = [measure(scene) for scene in scenes]
    elapsed = time.perf_counter() - start
    with_object = [r for r in results if r.sdf_zero_level_px is not None]
    print(f"### Vision accuracy: {len(scenes)} scenes, each an open frame (object between the fingers, "
          f"{len(with_object)} scenes with one) and a closed frame (no object); Theta in [0.3, 0.8], "
          f"plane 110-130 mm, 640x480, colour and depth noise, depth holes ({elapsed:.1f} s)\n")
    print("| quantity | worst | mean of per-scene worst | required |")
    print("| --- | --- | --- | --- |")
    rows = [
        ("base (px), both frames", [r.base_px for r in results], "<= 1.5"),
        ("tip (px), both frames", [r.tip_px for r in results], "<= 1.5"),
        ("Theta, eq. 4 (rad), closed frame", [r.theta_rad for r in results], "<= 0.01"),
        ("L, eq. 5 (%), open frame", [r.length_pct for r in results], "<= 1"),
        (f"observed positions, N = {N_LINKS} (px), closed frame", [r.observed_px for r in results], ""),
        ("half-thickness r (mm)", [r.half_thickness_mm for r in results], ""),
        ("SDF zero level to the true outline (px)", [r.sdf_zero_level_px for r in with_object], "<= 1"),
        ("abs(SDF) on the true outline, off sharp apexes (px)", [r.sdf_outline_px for r in with_object], ""),
        ("abs(SDF) on the true outline, everywhere (px)", [r.sdf_apex_px for r in with_object], ""),
    ]
    for name, values, required in rows:
        print(f"| {name} | {max(values):.4g} | {statistics.fmean(values):.4g} | {required} |")
    found = sum(r.fingers_found for r in results)
    print(f"| fingers found and matching the truth | {found}/{4 * len(results)} | | all |\n")

    frames = [render(scene.scene(closed=bool(i % 2)), INTRINSICS) for i, scene in enumerate(scenes[:8])]
    seconds = time_backends(frames)
    print(f"### Segmentation backends: a batch of {len(frames)} frames at 640x480 (best of 3, after a warm-up)\n")
    print("| backend | batch (ms) | per frame (ms) | relative to OpenCV |")
    print("| --- | --- | --- | --- |")
    for backend, label in (("opencv", "OpenCV (default)"), ("kornia", "kornia on torch CPU")):
        t = seconds[backend]
        print(f"| {label} | {1e3 * t:.0f} | {1e3 * t / len(frames):.1f} | {t / seconds['opencv']:.1f}x |")
    print(f"\nThe backends' masks differ on at most {100 * backend_disagreement(frames):.3f} % of the pixels "
          f"of a frame (tested bound: 0.5 %).")


if __name__ == "__main__":
    main()
