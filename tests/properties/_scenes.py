"""Random scenes for the property tests: rendered frames turned into the core's SDF, and the checks.

Every scene is rendered at one image size (320 x 240, ``synthetic.render``) and goes
through the frame -> SDF pipeline a user's frame goes through (``segment``, ``PlaneCamera``,
``object_sdf``), so every SDF grid has the same shape and the jitted estimate compiles once per
(method, N) for the whole run. The finger bases, Theta, L and r are drawn per scene as arrays
(traced, no recompilation); N is drawn from :data:`N_VALUES` (static: one compilation each).
"""

from __future__ import annotations

import math
from functools import cache

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import strategies as st

from softgrip_jax import (ContactConfig, FingerModel, MechanicsConfig, SDFGrid, chain_stations, estimate,
                          forward_kinematics, sweep_shape)
from softgrip_vision.geometry import PlaneCamera
from softgrip_vision.object_sdf import object_sdf
from softgrip_vision.segmentation import segment
from synthetic.render import Scene, d405_intrinsics, render
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import shape
from softgrip_jax import as_estimator

# 320 x 240 (about 0.62 mm per pixel at the 120 mm gripper plane, 200 x 150 mm in view): a quarter of
# the pixels of the D405's 640 x 480, so that rendering and segmenting a scene stays well under a second.
INTRINSICS = d405_intrinsics(320, 240)
SHAPES = ("circle", "square", "clover", "star_a", "triangle_a", "ellipse", "rounded_rect", "heart",
          "crescent", "cross", "l_shape")
N_VALUES = (5, 16)  # static: each value compiles once per method
BATCH = 24  # finger bases per scene, one vmapped call
CONFIG = ContactConfig()
MECHANICS = MechanicsConfig()


class Drawn:
    """One random scene: the rendered object's SDF, a finger and BATCH finger bases (mm).

    (A plain class, so that hypothesis reports a failing scene by its description.)
    """

    def __init__(self, sdf: SDFGrid, finger: FingerModel, bases: np.ndarray, description: str):
        self.sdf, self.finger, self.bases, self.description = sdf, finger, bases, description

    def __repr__(self) -> str:
        return f"Drawn({self.description})"


@st.composite
def scenes(draw) -> Drawn:
    name = draw(st.sampled_from(SHAPES))
    size = draw(st.floats(8.0, 40.0))
    angle = draw(st.floats(0.0, 2.0 * math.pi))
    centre = np.array([draw(st.floats(-25.0, 25.0)), draw(st.floats(0.0, 25.0))])
    theta = draw(st.floats(0.05, 1.3))
    length = draw(st.floats(25.0, 60.0))
    r = draw(st.floats(1.0, 5.0))
    n_links = draw(st.sampled_from(N_VALUES))
    seed = draw(st.integers(0, 2**16))
    polygon = shape(name, size, angle) + centre
    # A gripper in view (segmentation finds the gripper plane's depth from its fingers), near the
    # top of the image and clear of the object; the bases below are drawn around the object, where
    # fingers close onto it.
    fingers = gripper_centrelines((0.0, -70.0), 60.0, 20.0)
    frame = render(Scene(fingers, half_thickness=3.0, object_polygon=polygon, seed=seed), INTRINSICS)
    seg = segment(frame)
    sdf = object_sdf(seg.object, PlaneCamera.from_frame(frame, seg.fingers))
    rng = np.random.default_rng(seed)
    bases = centre + np.column_stack([rng.uniform(-length, 0.5 * size, BATCH),
                                      rng.uniform(-length - size, -0.2 * size, BATCH)])
    bases[:, 1] = np.maximum(bases[:, 1], -72.0)  # inside the image (y from about -75 mm)
    finger = FingerModel(length=length, theta_entire=theta, half_thickness=r, n_links=n_links)
    return Drawn(sdf, finger, bases.astype(np.float32),
                 f"{name} {size:.1f} mm at {centre.round(1).tolist()}, angle {angle:.2f}, Theta {theta:.3f}, "
                 f"L {length:.1f}, r {r:.2f}, N {n_links}, seed {seed}")


@cache
def estimator(method: str):
    """``(finger, sdf, bases (B, 2)) -> Estimate`` batched, jitted once per (method, N, shapes)."""

    @eqx.filter_jit
    def run(finger, sdf, bases):
        chosen = as_estimator(method=method, mechanics=MECHANICS)
        return jax.vmap(lambda b: estimate(finger, sdf, b, CONFIG, estimator=chosen))(bases)

    return run


def dense_points(joints: np.ndarray, per_link: int = 20) -> np.ndarray:
    """(..., N per_link + 1, 2) points along each chain's links, base to tip."""
    t = np.arange(per_link) / per_link
    inner = joints[..., :-1, None, :] + t[:, None] * (joints[..., 1:, None, :] - joints[..., :-1, None, :])
    inner = inner.reshape(*joints.shape[:-2], -1, 2)
    return np.concatenate([inner, joints[..., -1:, :]], axis=-2)


@cache
def _sweep_clearance(n_links: int, n_s: int, per_link: int):
    @eqx.filter_jit
    def run(finger, sdf, bases):
        s = finger.theta_entire * jnp.linspace(0.0, 1.0, n_s)

        def one(base, s_k):
            joints = forward_kinematics(base, *sweep_shape(finger, s_k, CONFIG.sweep), finger.length)
            return jnp.min(sdf.distance(chain_stations(joints, finger.length, per_link)[0]))

        return jax.vmap(lambda b: jax.vmap(lambda s_k: one(b, s_k))(s))(bases) - finger.half_thickness

    return run


def sweep_clearance(finger: FingerModel, sdf: SDFGrid, bases) -> np.ndarray:
    """(B, S) brute force: the closing finger's least clearance (mm) at S = 241 values of s in
    [0, Theta], on 60 or more centreline points; independent of the estimator's bracket and root."""
    per_link = max(1, -(-60 // finger.n_links))
    return np.asarray(_sweep_clearance(finger.n_links, 241, per_link)(finger, sdf, jnp.asarray(bases)))


def graze_tolerance(finger: FingerModel) -> float:
    """How deep (mm) a graze the estimator's contact sweep may miss (ContactConfig's docstring):
    the tip travels L Theta / (n_sweep - 1) between bracket values and a graze shallower than
    travel^2 / (8 r) can fall between two; stations (L / (N per_link) apart) can miss a corner
    by spacing^2 / (8 r) more."""
    length, theta, r = float(finger.length), float(finger.theta_entire), float(finger.half_thickness)
    travel = length * theta / (CONFIG.n_sweep - 1)
    spacing = length / (finger.n_links * CONFIG.per_link(finger.n_links))
    return (travel**2 + spacing**2) / (8.0 * r)
