"""Grasp quality (issue 30): the score's Ferrari-Canny epsilon against an independent reference,
what it ranks first, and what it costs.

Run from the repository root:

    .venv/bin/python benchmarks/bench_quality.py                    # every part, full size
    .venv/bin/python benchmarks/bench_quality.py --size quick       # every part, small
    .venv/bin/python benchmarks/bench_quality.py --part hull,ranking --json

Parts (``--part``, comma-separated):

* ``hull``: random candidates (poses uniform in :data:`HULL_BOX` around the paper's five objects
  and two concave ones, both estimators, one random mu in [0.2, 1.0] per block of
  :data:`HULL_BLOCK` candidates). Each candidate's wrenches are rebuilt in numpy from
  ``Score.contacts`` (:func:`reference_wrenches`, written here from the formula, not the core's
  ``edge_wrenches``) and the epsilon taken from ``scipy.spatial.ConvexHull``'s facets
  (:func:`reference_epsilon`); compared with ``Score.quality`` on the valid candidates.
* ``ranking``: a grid of 11 x 18 x 11 poses (x +-10 mm, y from -30 to +4 mm, angle +-0.2 rad)
  about the pose that puts the object between the fingers at mid-length (:data:`BOX`), on each of the paper's five objects, both
  estimators: valid, closure, and whether the top 20 are in force closure with both fingers touching.
* ``variants``: the same on frames rendered with renderer variants, through vision: a one-frame
  calibration (closed frame without object, open frame with it), ``softgrip_vision.scene.frame_scene`` (the
  object's SDF grid from the open frame, the profile's gripper) and a grid around the frame's pose.
* ``throughput``: candidates/s of ``score`` with both estimators on a grid where most fingers
  touch, against ``estimate_grasp_batch`` on the same poses and chunks (the closest call without
  the quality and score terms), and compilations counted across calls with new ``ScoreWeights``.
* ``quality_cost``: the same grid, ``score`` against ``score`` with the quality's contacts and hull
  replaced by constants (patched in this process, compiled anew): what the quality alone adds.
* ``robust``: the same grid (a quarter of its poses), ``score`` with an ``Uncertainty`` of 16
  draws and linearised (``linear=True``) against the nominal score, both estimators, each ranked
  against 256 draws of the same uncertainty.

Objects are outlines of :mod:`synthetic.shapes` (30 mm bounding circle) centred at
:data:`OBJECT_CENTRE_MM`, as :class:`softgrip_jax.PolygonSDF` resampled to :data:`VERTICES`
vertices (every corner kept, points added along the edges: the same exact distance, and one
compiled program for all objects). Gripper: L = 52 mm, Theta = 0.55 rad, r = 4 mm, N = 20, W = 56 mm.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import ConvexHull, QhullError

_ROOT = Path(__file__).resolve().parents[1]
for _path in (str(_ROOT), str(_ROOT / "benchmarks")):
    if _path not in sys.path:
        sys.path.insert(0, _path)

from _machine import describe  # noqa: E402

from softgrip_jax import (FingerModel, Geometric, Gripper, Mechanics, PolygonSDF, SDFGrid, ScoreWeights,  # noqa: E402
                          estimate_grasp_batch, score)
from synthetic.shapes import ACCURACY_SET, shape  # noqa: E402

LENGTH_MM = 52.0
THETA = 0.55
HALF_THICKNESS_MM = 4.0
N_LINKS = 20
BASE_SEPARATION_MM = 56.0
OBJECT_SIZE_MM = 30.0
OBJECT_CENTRE_MM = (0.0, 38.0)
PAPER_OBJECTS: tuple[str, ...] = ACCURACY_SET
CONCAVE_OBJECTS: tuple[str, ...] = ("crescent", "l_shape")
#: Vertices of every object's polygon (the most any of the objects above has: the crescent's 288).
VERTICES = 288
#: The ranking grids' offsets from the centred pose, low and high: x mm, y mm (from the object
#: 4 mm nearer the base than mid-length to 30 mm farther, past the fingertips: the approach depths
#: a planner searches), angle rad.
BOX = ((-10.0, -30.0, -0.2), (10.0, 4.0, 0.2))
#: The hull part's pose box: x, y from the centred pose (mm) and angle (rad), low and high; lower
#: than the ranking's box too (the fingers reach farther round the object: more force closure).
HULL_BOX = ((-10.0, -18.0, -0.2), (10.0, 10.0, 0.2))
#: Candidates scored together with one mu in the hull part.
HULL_BLOCK = 16
MU_RANGE = (0.2, 1.0)
TOP = 20
CHUNK = 2048

SIZES = {  # --size: hull candidates, ranking and variant grids' values per axis, variants, throughput poses
    "full": dict(hull=1000, counts=(11, 18, 11), variants=("default", "tilt 10 deg", "lighting and noise",
                                                        "round fingers"), throughput=8192),
    "quick": dict(hull=224, counts=(5, 9, 5), variants=("default", "tilt 10 deg"), throughput=2048),
}


def estimators() -> dict:
    """The two deformation estimates by name."""
    return {"geometric": Geometric(), "mechanics": Mechanics()}


def make_gripper(n_links: int = N_LINKS, base_separation_mm: float = BASE_SEPARATION_MM) -> Gripper:
    """The benchmark's gripper: two equal fingers (L 52 mm, Theta 0.55 rad, r 4 mm) 56 mm apart."""
    finger = FingerModel(length=LENGTH_MM, theta_entire=THETA, half_thickness=HALF_THICKNESS_MM, n_links=n_links)
    return Gripper(left=finger, right=finger, base_separation=base_separation_mm)


def resample_outline(polygon: np.ndarray, count: int) -> np.ndarray:
    """The polygon (V, 2) mm with ``count`` >= V vertices: every corner kept, the extra ones spread
    evenly along the edges (in proportion to their length), so the outline is unchanged."""
    polygon = np.asarray(polygon, np.float64)
    ends = np.roll(polygon, -1, axis=0)
    lengths = np.hypot(*(ends - polygon).T)
    share = lengths / lengths.sum() * (count - len(polygon))
    extra = np.floor(share).astype(int)
    extra[np.argsort(extra - share)[: count - len(polygon) - extra.sum()]] += 1
    parts = [a + (np.arange(k + 1) / (k + 1))[:, None] * (b - a) for a, b, k in zip(polygon, ends, extra)]
    return np.concatenate(parts)


def object_outline(name: str, centre_mm=OBJECT_CENTRE_MM) -> np.ndarray:
    """(V, 2) mm: the named outline (30 mm bounding circle) about ``centre_mm``."""
    return shape(name, OBJECT_SIZE_MM) + np.asarray(centre_mm)


def object_sdf(name: str, centre_mm=OBJECT_CENTRE_MM) -> PolygonSDF:
    """The named object's exact SDF about ``centre_mm``, float32, :data:`VERTICES` vertices."""
    return PolygonSDF(jnp.asarray(resample_outline(object_outline(name, centre_mm), VERTICES), jnp.float32))


def centred_pose() -> np.ndarray:
    """(3,) the pose that puts the object's centre between the fingers at mid-length."""
    return np.array([OBJECT_CENTRE_MM[0], OBJECT_CENTRE_MM[1] - LENGTH_MM / 2.0, 0.0])


def pose_grid(centre: np.ndarray, counts: tuple[int, int, int], box=BOX) -> np.ndarray:
    """(prod(counts), 3) float32 poses: a regular grid of ``counts`` values per axis over
    centre + box[0] to centre + box[1]."""
    axes = [np.linspace(c + lo, c + hi, n) for c, lo, hi, n in zip(centre, *box, counts)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# The independent reference


def reference_wrenches(points, normals, touching, mu: float, centroid, rho: float) -> np.ndarray:
    """(2T, 3) float64 planar wrenches of the T touching contacts' friction-cone edges.

    Each contact (point p mm, outward unit normal n) pushes along -n; the cone's edges are the unit
    forces normalize(-n + mu t) and normalize(-n - mu t), t = (-n_y, n_x); each gives the wrench
    (f_x, f_y, ((p - c) x f) / rho), c the centroid (mm), rho (mm). Contacts not touching give none.
    """
    p = np.asarray(points, np.float64).reshape(-1, 2)[np.asarray(touching).reshape(-1)]
    n = np.asarray(normals, np.float64).reshape(-1, 2)[np.asarray(touching).reshape(-1)]
    t = np.column_stack([-n[:, 1], n[:, 0]])
    rows = []
    for sign in (1.0, -1.0):
        f = -n + sign * mu * t
        f /= np.linalg.norm(f, axis=1, keepdims=True)
        lever = p - np.asarray(centroid, np.float64)
        rows.append(np.column_stack([f, (lever[:, 0] * f[:, 1] - lever[:, 1] * f[:, 0]) / float(rho)]))
    return np.concatenate(rows).reshape(-1, 3)


def reference_epsilon(wrenches: np.ndarray) -> float:
    """L1 Ferrari-Canny epsilon by Qhull: the smallest depth of the origin below the hull's facets
    (``-offset`` of each unit-normal facet equation), 0 unless every facet's is positive; a hull
    Qhull cannot build (fewer than 4 wrenches, flat) is 0."""
    if len(wrenches) < 4:
        return 0.0
    try:
        hull = ConvexHull(wrenches)
    except QhullError:
        return 0.0
    depth = -hull.equations[:, 3]
    return float(depth.min()) if np.all(depth > 0) else 0.0


# ---------------------------------------------------------------------------------------------
# Part: hull


def hull_part(n_candidates: int, seed: int = 30) -> dict:
    """Score.quality against the reference on ``n_candidates`` random candidates (rounded up to
    whole blocks spread over objects and estimators); see the module docstring."""
    rng = np.random.default_rng(seed)
    gripper = make_gripper()
    groups = [(name, est) for name in PAPER_OBJECTS + CONCAVE_OBJECTS for est in estimators()]
    blocks = math.ceil(n_candidates / HULL_BLOCK)
    worst = {"rel_error": 0.0}
    counts = {"drawn": 0, "valid": 0, "compared": 0, "closure": 0, "near_zero": 0, "none": 0,
              "closure_flag_disagrees": 0, "none_but_quality": 0}
    errors = []
    for b in range(blocks):
        name, est_name = groups[b % len(groups)]
        mu = float(rng.uniform(*MU_RANGE))
        poses = centred_pose() + rng.uniform(*HULL_BOX, (HULL_BLOCK, 3))
        result = score(gripper, object_sdf(name), jnp.asarray(poses, jnp.float32), ScoreWeights(mu=mu),
                       estimator=estimators()[est_name])
        result = jax.tree_util.tree_map(np.asarray, result)
        for i in range(HULL_BLOCK):
            counts["drawn"] += 1
            if not result.valid[i]:
                continue
            counts["valid"] += 1
            c = result.contacts
            ref = reference_epsilon(reference_wrenches(c.points[i], c.normals[i], c.touching[i], mu,
                                                       result.centroid[i], result.rho[i]))
            ours = float(result.quality[i])
            counts["closure_flag_disagrees"] += int(bool(result.force_closure[i]) != (ref > 0))
            if ref > 1e-3:
                counts["closure"] += 1
                rel = abs(ours - ref) / ref
                errors.append(rel)
                if rel >= worst["rel_error"]:
                    worst = {"rel_error": rel, "object": name, "estimator": est_name, "mu": mu,
                             "pose": poses[i].round(3).tolist(), "quality": ours, "reference": ref}
            elif ref > 0:
                counts["near_zero"] += 1
            else:
                counts["none"] += 1
                counts["none_but_quality"] += int(ours > 1e-4)
    counts["compared"] = counts["closure"]
    return {"counts": counts, "worst": worst,
            "median_rel_error": float(np.median(errors)) if errors else None}


# ---------------------------------------------------------------------------------------------
# Part: ranking (exact geometry and rendered frames)


def ranking_row(result, poses: np.ndarray, top: int = TOP) -> dict:
    """Counts of one scored grid (numpy :class:`softgrip_jax.Score`): valid, closure, and of the
    ``top`` best, how many are in force closure and how many have both fingers touching (contact
    case not none); the best pose (x mm, y mm, angle rad) and its quality."""
    order = np.argsort(-result.score, kind="stable")[:top]
    both = (result.grasp.left.case != 0) & (result.grasp.right.case != 0) & result.valid
    best = int(order[0])
    return {"poses": int(len(poses)), "valid": int(result.valid.sum()), "closure": int(result.force_closure.sum()),
            "top_closure": int(result.force_closure[order].sum()), "top_both_touching": int(both[order].sum()),
            "top": int(len(order)), "best_pose": [round(float(v), 3) for v in poses[best]],
            "best_quality": float(result.quality[best]), "best_score": float(result.score[best])}


def ranking_part(counts: tuple[int, int, int], names: tuple[str, ...] = PAPER_OBJECTS) -> list[dict]:
    """One :func:`ranking_row` per object and estimator on the exact outlines (mu 0.5)."""
    gripper = make_gripper()
    poses = pose_grid(centred_pose(), counts)
    rows = []
    for name in names:
        for est_name, est in estimators().items():
            result = jax.tree_util.tree_map(np.asarray, score(gripper, object_sdf(name), jnp.asarray(poses),
                                                              estimator=est))
            rows.append({"object": name, "estimator": est_name, **ranking_row(result, poses)})
    return rows


@dataclass(frozen=True)
class RenderedScene:
    """A frame's worth of set-up in the gripper plane (mm): the gripper's centre between the bases
    and the object's centre, both at the benchmark's relative placement (object at mid-length)."""

    index: int
    object_name: str
    #: The closed calibration frame needs its tips apart: 2 (L sin^2 Theta / Theta + r) + 8 mm.
    base_separation_mm: float = 68.0
    gripper_centre_mm: tuple[float, float] = (0.0, -LENGTH_MM / 2.0)
    object_centre_mm: tuple[float, float] = (0.0, 0.0)


def vision_scene(setup: RenderedScene, variant: str):
    """Render the closed (no object) and open (object) frames as ``variant``, calibrate from the
    pair (``softgrip_calib.one_frame.one_frame_from_frames``, N = 20) and build the open frame's
    :class:`softgrip_vision.scene.Scene` (the object's SDF grid from the frame, the profile's gripper)."""
    from benchmarks.vision_accuracy import INTRINSICS, AccuracyScene, variant_scenes
    from softgrip_calib.one_frame import one_frame_from_frames
    from synthetic.render import render
    from softgrip_vision.scene import frame_scene

    accuracy = AccuracyScene(
        index=setup.index, theta=THETA, center_mm=setup.gripper_centre_mm, base_separation_mm=setup.base_separation_mm,
        plane_depth_mm=120.0, object_name=setup.object_name, object_size_mm=OBJECT_SIZE_MM, object_angle=0.0,
        object_center_mm=setup.object_centre_mm, color_noise_sigma=3.0, n_depth_holes=5)
    opened, closed = variant_scenes(accuracy, variant)
    open_frame, closed_frame = render(opened, INTRINSICS), render(closed, INTRINSICS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # e.g. the tilt warning: the scene is what is measured here
        profile = one_frame_from_frames(closed_frame, open_frame, N_LINKS)
        return frame_scene(open_frame, profile, warn=lambda _: None)


#: The variants table's first rows: the rendered set-up's exact outline and gripper, without vision.
EXACT = "exact outline"


def exact_rows(counts: tuple[int, int, int], names: tuple[str, ...]) -> list[dict]:
    """:func:`ranking_row` per object and estimator for the rendered set-up (:class:`RenderedScene`)
    on the exact outline and the true gripper (W 68 mm), the grid about the true pose."""
    rows = []
    for k, name in enumerate(names):
        setup = RenderedScene(index=k, object_name=name)
        gripper = make_gripper(base_separation_mm=setup.base_separation_mm)
        poses = pose_grid(np.array([*setup.gripper_centre_mm, 0.0]), counts)
        sdf = object_sdf(name, setup.object_centre_mm)
        for est_name, est in estimators().items():
            result = jax.tree_util.tree_map(np.asarray, score(gripper, sdf, jnp.asarray(poses), estimator=est))
            rows.append({"variant": EXACT, "object": name, "estimator": est_name, "pose_error_mm": 0.0,
                         "vision_s": 0.0, **ranking_row(result, poses)})
    return rows


def variants_part(counts: tuple[int, int, int], variants: tuple[str, ...], names: tuple[str, ...] = PAPER_OBJECTS) -> list[dict]:
    """One :func:`ranking_row` per variant, object and estimator, through vision (mu 0.5); the grid
    is about the frame's measured pose, and ``pose_error_mm`` says how far that is from the truth
    (in the measured plane's millimetres). First the same set-up on its exact geometry (:func:`exact_rows`)."""
    rows = exact_rows(counts, names)
    for variant in variants:
        for k, name in enumerate(names):
            setup = RenderedScene(index=k, object_name=name)
            t0 = time.perf_counter()
            scene = vision_scene(setup, variant)
            vision_s = time.perf_counter() - t0
            poses = pose_grid(np.asarray(scene.pose), counts)
            for est_name, est in estimators().items():
                result = scene.score(poses, estimator=est)
                rows.append({"variant": variant, "object": name, "estimator": est_name,
                             "pose_error_mm": round(float(np.hypot(*(scene.pose[:2] - setup.gripper_centre_mm))), 3),
                             "vision_s": round(vision_s, 1), **ranking_row(result, poses)})
    return rows


# ---------------------------------------------------------------------------------------------
# Part: throughput


class CompileCounter:
    """Counts JAX traces and backend compilations while registered (``jax.monitoring`` events)."""

    def __init__(self):
        from jax._src import dispatch

        self.names = {dispatch.JAXPR_TRACE_EVENT: "traces", dispatch.BACKEND_COMPILE_EVENT: "compiles"}
        self.counts = {"traces": 0, "compiles": 0}
        jax.monitoring.register_event_duration_secs_listener(self._on_event)

    def _on_event(self, event: str, _duration: float, **_kwargs) -> None:
        if event in self.names:
            self.counts[self.names[event]] += 1

    def snapshot(self) -> dict:
        return dict(self.counts)


def best_of(call, repeats: int = 3) -> float:
    """The fastest of ``repeats`` timed calls (s), each until its result is ready."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
    return min(times)


def throughput_grid(n_poses: int, seed: int = 1) -> np.ndarray:
    """(n_poses, 3) float32 poses uniform in x +-5 mm, y from the centred pose -10 to +2 mm, angle
    +-0.1 rad: a planner's neighbourhood where most fingers close onto the disc."""
    rng = np.random.default_rng(seed)
    low, high = centred_pose() + (-5.0, -10.0, -0.1), centred_pose() + (5.0, 2.0, 0.1)
    return rng.uniform(low, high, (n_poses, 3)).astype(np.float32)


def disc_grid() -> SDFGrid:
    """A 480 x 640 SDF grid at 0.31 mm/px (a D405 frame at 120 mm) of the 30 mm disc at the object centre."""
    spacing = 120.0 / 385.0
    disc = PolygonSDF(jnp.asarray(object_outline("circle"), jnp.float32))
    origin = (OBJECT_CENTRE_MM[0] - 320 * spacing, OBJECT_CENTRE_MM[1] - 240 * spacing)
    return SDFGrid.sample(disc, origin=origin, spacing=(spacing, spacing), shape=(480, 640))


def throughput_part(n_poses: int) -> dict:
    """Candidates/s of ``score`` and ``estimate_grasp_batch`` (both estimators, chunks of
    :data:`CHUNK`, best of 3 after a compiling call), and compilations across new ScoreWeights."""
    from softgrip_jax._score import _score_one_device

    counter = CompileCounter()
    gripper, sdf = make_gripper(), disc_grid()
    poses = jnp.asarray(throughput_grid(n_poses))
    out: dict = {"poses": n_poses, "chunk": CHUNK, "rates": {}, "compile_s": {}}
    for est_name, est in estimators().items():
        calls = {"score": lambda est=est: score(gripper, sdf, poses, chunk_size=CHUNK, estimator=est),
                 "estimate_grasp_batch": lambda est=est: estimate_grasp_batch(gripper, sdf, poses, chunk_size=CHUNK,
                                                                              estimator=est)}
        for call_name, call in calls.items():
            before = counter.snapshot()
            t0 = time.perf_counter()
            first = jax.block_until_ready(call())
            first_s = time.perf_counter() - t0
            after = counter.snapshot()  # the counter's check: a first call traces and compiles
            out.setdefault("first_call", {})[f"{call_name} {est_name}"] = {k: after[k] - before[k] for k in after}
            best = best_of(call)
            out["rates"][f"{call_name} {est_name}"] = n_poses / best
            out["compile_s"][f"{call_name} {est_name}"] = first_s - best
            if call_name == "estimate_grasp_batch":
                touching = np.asarray((first.left.case != 0) & first.left.valid).mean() / 2 + np.asarray(
                    (first.right.case != 0) & first.right.valid).mean() / 2
                out.setdefault("fingers_touching", {})[est_name] = float(touching)
    rates = out["rates"]
    out["mechanics_over_geometric"] = rates["score geometric"] / rates["score mechanics"]  # time per candidate
    out["score_over_estimate"] = {e: rates[f"estimate_grasp_batch {e}"] / rates[f"score {e}"] for e in estimators()}
    out["score_added_us"] = {e: 1e6 * (1.0 / rates[f"score {e}"] - 1.0 / rates[f"estimate_grasp_batch {e}"])
                             for e in estimators()}
    out["new_weights"] = new_weights_calls(gripper, sdf, poses, counter, _score_one_device)
    return out


def new_weights_calls(gripper, sdf, poses, counter: CompileCounter, jitted_score) -> list[dict]:
    """Score the same poses (geometric) with several new ScoreWeights: per call its time (s) and the
    traces / compilations / jit cache entries it added (all 0: weights are run-time arrays)."""
    rows = []
    settings = [dict(mu=0.8), dict(mu=0.3, touch=2.0, wrap=0.5), dict(tip_only=0.9, penetration=0.1, event=0.0,
                                                                      contact_band=0.5, max_penetration=0.8)]
    for setting in settings:
        before, cache = counter.snapshot(), jitted_score._jitted._cache_size()
        t0 = time.perf_counter()
        jax.block_until_ready(score(gripper, sdf, poses, ScoreWeights(**setting), chunk_size=CHUNK,
                                    estimator=Geometric()))
        seconds = time.perf_counter() - t0
        after = counter.snapshot()
        rows.append({"weights": setting, "seconds": seconds, "traces": after["traces"] - before["traces"],
                     "compiles": after["compiles"] - before["compiles"],
                     "jit_cache_entries": jitted_score._jitted._cache_size() - cache})
    return rows


def quality_cost_part(n_poses: int) -> dict:
    """What the grasp quality adds to ``score``, isolated: the same score with the quality's
    contacts and hull replaced by constants (``softgrip_jax._score``'s ``finger_contacts`` and
    ``closure_margin``, patched in this process only, programs compiled anew), best of 3 each, both
    estimators, interleaved A, B, A, B so that load drifts hit both."""
    import softgrip_jax._score as score_module
    from softgrip_jax._quality import FingerContacts

    def no_contacts(sdf, stations, half_thickness, band, k=3, distance=None):
        zero = jnp.zeros((k, 2), stations.dtype)
        return FingerContacts(points=zero, normals=zero, forces=zero, touching=jnp.zeros(k, bool)), jnp.zeros(k, int)

    gripper, sdf = make_gripper(), disc_grid()
    poses = jnp.asarray(throughput_grid(n_poses))
    real = (score_module.finger_contacts, score_module.closure_margin)
    stub = (no_contacts, lambda w, active: jnp.zeros((), w.dtype))
    out: dict = {"poses": n_poses, "rates": {}}
    for est_name, est in estimators().items():
        times = {"with quality": [], "without": []}
        for _ in range(2):
            for label, (contacts_fn, hull_fn) in (("with quality", real), ("without", stub)):
                score_module.finger_contacts, score_module.closure_margin = contacts_fn, hull_fn
                jax.clear_caches()  # trace again with the functions in place
                try:
                    call = lambda: score(gripper, sdf, poses, chunk_size=CHUNK, estimator=est)  # noqa: E731
                    jax.block_until_ready(call())
                    times[label].append(best_of(call))
                finally:
                    score_module.finger_contacts, score_module.closure_margin = real
        for label, t in times.items():
            out["rates"][f"{label} {est_name}"] = n_poses / min(t)
        out.setdefault("added", {})[est_name] = min(times["with quality"]) / min(times["without"]) - 1.0
    return out


def _agreement(result, reference, valid) -> dict:
    """How one robust result ranks against the reference (many draws): top 20 shared, Spearman's
    rank correlation of the score over the candidates in force closure (the others rank by the
    nominal progress alike), and the largest and median differences of P(closure) and the
    expected quality over the candidates it drew."""
    from scipy.stats import spearmanr

    closed = valid & np.asarray(reference.force_closure)  # the robust values rank these
    got, ref = (np.asarray(r.score)[closed] for r in (result, reference))
    drawn = valid & np.isfinite(np.asarray(result.p_closure))  # NaN: not drawn (outside the reach)
    p = np.abs(np.asarray(result.p_closure) - np.asarray(reference.p_closure))[drawn]
    q = np.abs(np.asarray(result.quality_mean) - np.asarray(reference.quality_mean))[drawn]
    top = [set(np.argsort(-np.asarray(r.score))[:TOP].tolist()) for r in (result, reference)]
    return {"top20_shared": len(top[0] & top[1]), "spearman": float(spearmanr(got, ref).statistic),
            "p_closure_max": float(p.max()), "p_closure_median": float(np.median(p)),
            "quality_mean_max": float(q.max()), "quality_mean_median": float(np.median(q))}


def robust_part(n_poses: int, samples: int = 16, reference_samples: int = 256) -> dict:
    """Candidates/s of ``score`` with an ``Uncertainty`` of ``samples`` draws and with the
    linearisation (``linear=True``), against the nominal score, on the throughput grid (both
    estimators); and how each ranks against ``reference_samples`` draws of the same uncertainty."""
    from softgrip_jax import Uncertainty

    gripper, sdf = make_gripper(), disc_grid()
    poses = jnp.asarray(throughput_grid(n_poses))
    spread = dict(pose_mm=0.5, pose_rad=0.01, mu_spread=0.2, theta=0.01, contour_mm=0.2)
    settings = {"nominal": None, f"K = {samples}": Uncertainty(samples=samples, **spread),
                "linear": Uncertainty(linear=True, **spread),
                # The reference draws every valid candidate, however far from closure.
                f"K = {reference_samples}": Uncertainty(samples=reference_samples, reach=math.inf, **spread)}
    out: dict = {"poses": n_poses, "samples": samples, "reference_samples": reference_samples, "spread": spread,
                 "rates": {}, "closure": {}, "agreement": {}}
    for est_name, est in estimators().items():
        results = {}
        for label, uncertainty in settings.items():
            call = lambda uncertainty=uncertainty: score(gripper, sdf, poses, chunk_size=CHUNK, estimator=est,  # noqa: E731
                                                        uncertainty=uncertainty)
            results[label] = jax.block_until_ready(call())
            repeats = 1 if label == f"K = {reference_samples}" else 2
            out["rates"][f"{label}|{est_name}"] = n_poses / best_of(call, repeats=repeats)
            out["closure"][f"{label}|{est_name}"] = int(np.asarray(results[label].force_closure).sum())
        if est_name == "geometric":  # new spreads, seed and reach: run-time values, no new program
            from softgrip_jax._score import _score_one_device

            counter = CompileCounter()
            for setting in (dict(pose_mm=1.0, pose_rad=0.02, mu_spread=0.1), dict(contour_mm=0.4, theta=0.02,
                                                                                   seed=7, reach=0.3)):
                u = Uncertainty(samples=samples, **{**spread, **setting})
                before, cache = counter.snapshot(), _score_one_device._jitted._cache_size()
                t0 = time.perf_counter()
                jax.block_until_ready(score(gripper, sdf, poses, chunk_size=CHUNK, estimator=est, uncertainty=u))
                after = counter.snapshot()
                out.setdefault("new_uncertainty", []).append(
                    {"setting": setting, "seconds": time.perf_counter() - t0,
                     "traces": after["traces"] - before["traces"], "compiles": after["compiles"] - before["compiles"],
                     "jit_cache_entries": _score_one_device._jitted._cache_size() - cache})
        valid = np.asarray(results["nominal"].valid)
        reference = results[f"K = {reference_samples}"]
        for label in ("nominal", f"K = {samples}", "linear"):
            out["agreement"][f"{label}|{est_name}"] = _agreement(results[label], reference, valid)
        # What the reach leaves out: the reference's P(closure) of the candidates K draws skip.
        margin = np.asarray(results["nominal"].margin)
        skipped = valid & (margin <= -settings[f"K = {samples}"].reach)
        p_ref = np.asarray(reference.p_closure)
        out.setdefault("skipped", {})[est_name] = {
            "count": int(skipped.sum()), "valid": int(valid.sum()),
            "largest_reference_p": float(p_ref[skipped].max()) if skipped.any() else 0.0,
            "reach": float(settings[f"K = {samples}"].reach)}
    return out


# ---------------------------------------------------------------------------------------------
# Output


def hull_table(part: dict) -> list[str]:
    c, w = part["counts"], part["worst"]
    lines = ["| candidates | valid | closure (ref > 1e-3) | 0 < ref <= 1e-3 | none (ref = 0) | "
             "closure flag disagrees | largest rel. error | median rel. error |",
             "|---|---|---|---|---|---|---|---|",
             f"| {c['drawn']:,} | {c['valid']:,} | {c['closure']:,} | {c['near_zero']:,} | {c['none']:,} | "
             f"{c['closure_flag_disagrees']} | {100 * w['rel_error']:.3f} % | "
             f"{100 * (part['median_rel_error'] or 0.0):.4f} % |"]
    if "object" in w:
        lines.append(f"\nLargest error: {w['object']}, {w['estimator']}, mu {w['mu']:.3f}, pose {w['pose']}: "
                     f"quality {w['quality']:.6f}, reference {w['reference']:.6f}.")
    return lines


def ranking_table(rows: list[dict], with_variant: bool = False) -> list[str]:
    head = ("| variant " if with_variant else "") + ("| object | estimator | poses | valid | closure | "
                                                     "top-20 closure | top-20 both touching | best pose (x, y, angle) "
                                                     "| best quality |")
    if with_variant:
        head += " pose error (mm) |"
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for r in rows:
        cells = ([r["variant"]] if with_variant else []) + [
            r["object"], r["estimator"], f"{r['poses']:,}", f"{r['valid']:,}", f"{r['closure']:,}",
            f"{r['top_closure']}/{r['top']}", f"{r['top_both_touching']}/{r['top']}",
            "({:.2f}, {:.2f}, {:.3f})".format(*r["best_pose"]), f"{r['best_quality']:.4f}"]
        if with_variant:
            cells.append(f"{r['pose_error_mm']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def throughput_table(part: dict) -> list[str]:
    rates, compile_s = part["rates"], part["compile_s"]
    lines = [f"{part['poses']:,} poses, chunks of {part['chunk']}; fingers touching (valid, case not none): "
             + ", ".join(f"{k} {100 * v:.1f} %" for k, v in part["fingers_touching"].items()), "",
             "| call | estimator | candidates/s | compile (s) | first call: traces / compilations |",
             "|---|---|---|---|---|"]
    for key, rate in rates.items():
        call, est = key.split(" ")
        first = part["first_call"][key]
        lines.append(f"| {call} | {est} | {rate:,.0f} | {compile_s[key]:.1f} | {first['traces']} / {first['compiles']} |")
    lines += ["", f"score's time per candidate, mechanics over geometric: {part['mechanics_over_geometric']:.2f}x; "
              "score over estimate_grasp_batch (what the quality and score terms add): "
              + ", ".join(f"{k} {v:.2f}x (+{part['score_added_us'][k]:.1f} us a candidate)"
                          for k, v in part["score_over_estimate"].items()), "",
              "| new ScoreWeights | call (s) | traces | compilations | jit cache entries added |", "|---|---|---|---|---|"]
    for r in part["new_weights"]:
        setting = ", ".join(f"{k}={v}" for k, v in r["weights"].items())
        lines.append(f"| {setting} | {r['seconds']:.3f} | {r['traces']} | {r['compiles']} | {r['jit_cache_entries']} |")
    return lines


def quality_cost_table(part: dict) -> list[str]:
    lines = [f"{part['poses']:,} poses (the throughput grid), chunks of {CHUNK}", "",
             "| score | estimator | candidates/s |", "|---|---|---|"]
    for key, rate in part["rates"].items():
        label, est = key.rsplit(" ", 1)
        lines.append(f"| {label} | {est} | {rate:,.0f} |")
    lines += ["", "the quality adds: " + ", ".join(f"{k} {100 * v:+.1f} %" for k, v in part["added"].items())]
    return lines


def robust_table(part: dict) -> list[str]:
    ref = f"K = {part['reference_samples']}"
    spread = ", ".join(f"{k} {v}" for k, v in part["spread"].items())
    lines = [f"{part['poses']:,} poses (the throughput grid), chunks of {CHUNK}; uncertainty: {spread}; the "
             f"reference: {ref} draws", "",
             f"| score | estimator | candidates/s | poses in closure | top 20 shared with {ref} | Spearman (score in closure) | "
             "P(closure) error max / median | expected-quality error max / median |",
             "|---|---|---|---|---|---|---|---|"]
    for key, rate in part["rates"].items():
        label, est = key.split("|")
        a = part["agreement"].get(key)
        agree = (f"{a['top20_shared']} | {a['spearman']:.3f} | {a['p_closure_max']:.3f} / {a['p_closure_median']:.4f} | "
                 f"{a['quality_mean_max']:.4f} / {a['quality_mean_median']:.5f}") if a else "| | |"
        lines.append(f"| {label} | {est} | {rate:,.0f} | {part['closure'][key]} | {agree} |")
    if part.get("new_uncertainty"):
        lines += ["", f"| new Uncertainty (K = {part['samples']}, geometric) | call (s) | traces | compilations | "
                      "jit cache entries added |", "|---|---|---|---|---|"]
        for r in part["new_uncertainty"]:
            setting = ", ".join(f"{k}={v}" for k, v in r["setting"].items())
            lines.append(f"| {setting} | {r['seconds']:.3f} | {r['traces']} | {r['compiles']} | {r['jit_cache_entries']} |")
    for est, sk in part.get("skipped", {}).items():
        lines.append(f"\n{est}: {sk['count']:,} of {sk['valid']:,} valid candidates lie farther than the reach "
                     f"({sk['reach']:g}) from closure and are not drawn; their largest P(closure) in the reference: "
                     f"{sk['largest_reference_p']:.3f}")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", default="hull,ranking,variants,throughput,quality_cost,robust",
                        help="comma-separated parts: hull, ranking, variants, throughput, quality_cost, robust "
                             "(default: all)")
    parser.add_argument("--size", choices=sorted(SIZES), default="full", help="full (default) or quick")
    parser.add_argument("--json", action="store_true", help="print the results as one JSON document")
    args = parser.parse_args(argv)
    parts = [p.strip() for p in args.part.split(",") if p.strip()]
    unknown = set(parts) - {"hull", "ranking", "variants", "throughput", "quality_cost", "robust"}
    if unknown:
        parser.error(f"unknown part(s): {', '.join(sorted(unknown))}")
    size = SIZES[args.size]
    command = "python benchmarks/bench_quality.py " + " ".join(argv if argv is not None else sys.argv[1:])
    results: dict = {"command": command.strip(), "machine": describe(), "size": args.size}
    say = (lambda *a, **k: None) if args.json else print
    say(f"`{results['command']}` on {results['machine']}\n")
    runners = {"hull": lambda: hull_part(size["hull"]), "ranking": lambda: ranking_part(size["counts"]),
               "variants": lambda: variants_part(size["counts"], size["variants"]),
               "throughput": lambda: throughput_part(size["throughput"]),
               "quality_cost": lambda: quality_cost_part(size["throughput"]),
               "robust": lambda: robust_part(size["throughput"] // 4)}
    tables = {"hull": hull_table, "ranking": ranking_table, "variants": lambda r: ranking_table(r, True),
              "throughput": throughput_table, "quality_cost": quality_cost_table, "robust": robust_table}
    for part in parts:
        t0 = time.perf_counter()
        results[part] = runners[part]()
        results[f"{part}_seconds"] = round(time.perf_counter() - t0, 1)
        say(f"### {part} ({results[f'{part}_seconds']} s)\n")
        say("\n".join(tables[part](results[part])) + "\n", flush=True)
    if args.json:
        print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
