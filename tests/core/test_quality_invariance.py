"""Grasp quality does not depend on where the scene is, how it is turned, or its size; and a grasp in
force closure outranks every grasp without, whatever the weights.

The scenes are moved, turned and scaled here, object and gripper together, and scored again with
the geometric estimate (N = 10, float32): the quality and the force-closure flag must not change.
Angles follow the project's convention (positive from +y toward +x: a pose's angle and
``synthetic.shapes``' rotation turn (0, 1) toward (1, 0)).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF, ScoreWeights, score
from synthetic.shapes import shape

CENTRE = np.array([0.0, 38.0])
#: Poses (x mm, y mm, angle rad) about the object: both kinds, force closure and none.
POSES = np.array([[3.0, 0.0, 0.1], [0.0, 0.0, 0.1], [-6.0, 2.0, 0.0], [3.0, -2.0, 0.0], [0.0, 12.0, 0.0],
                  [-3.0, 8.0, 0.05]])
#: float32 rounding of a moved scene (the qualities here are 0.07-0.14).
QUALITY_TOL = 1e-4


def gripper(scale: float = 1.0) -> Gripper:
    finger = FingerModel(length=52.0 * scale, theta_entire=0.55, half_thickness=4.0 * scale, n_links=10)
    return Gripper(left=finger, right=finger, base_separation=56.0 * scale)


def outline() -> np.ndarray:
    """A square (30 mm bounding circle, turned 0.3 rad) about CENTRE: flat sides and corners."""
    return shape("square", 30.0, 0.3) + CENTRE


def rotation(angle: float) -> np.ndarray:
    """Row-vector rotation (p @ R) turning (0, 1) toward (1, 0) by ``angle`` rad."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def scored(g: Gripper, vertices: np.ndarray, poses: np.ndarray, weights: ScoreWeights = ScoreWeights()):
    result = score(g, PolygonSDF(jnp.asarray(vertices, jnp.float32)), jnp.asarray(poses, jnp.float32), weights,
                   estimator=Geometric())
    return jax.tree_util.tree_map(np.asarray, result)


@pytest.fixture(scope="module")
def reference():
    result = scored(gripper(), outline(), POSES)
    assert result.valid.all()
    assert 0 < result.force_closure.sum() < len(POSES)  # both kinds are exercised
    return result


def assert_same_quality(moved, reference) -> None:
    np.testing.assert_array_equal(moved.force_closure, reference.force_closure)
    np.testing.assert_allclose(moved.quality, reference.quality, atol=QUALITY_TOL)


@pytest.mark.parametrize("shift", [(25.0, -13.0), (-140.0, 90.0)])
def test_moving_object_and_gripper_together_keeps_the_quality(reference, shift) -> None:
    poses = POSES + (*shift, 0.0)
    assert_same_quality(scored(gripper(), outline() + shift, poses), reference)


@pytest.mark.parametrize(("angle", "about"), [(0.7, (0.0, 0.0)), (-2.2, (10.0, 30.0)), (math.pi, (5.0, 5.0))])
def test_turning_object_and_gripper_together_keeps_the_quality(reference, angle, about) -> None:
    about = np.asarray(about)
    turn = lambda p: (p - about) @ rotation(angle) + about  # noqa: E731
    poses = np.column_stack([turn(POSES[:, :2]), POSES[:, 2] + angle])
    assert_same_quality(scored(gripper(), turn(outline()), poses), reference)


@pytest.mark.parametrize("s", [0.5, 2.5])
def test_scaling_object_and_gripper_together_keeps_the_quality(reference, s) -> None:
    """Lengths scale by s about the origin: the object, the fingers (L, r), W, the poses' x and y,
    and the one length among the weights, the contact band (mm)."""
    poses = np.column_stack([POSES[:, :2] * s, POSES[:, 2]])
    weights = ScoreWeights(contact_band=ScoreWeights().contact_band * s)
    assert_same_quality(scored(gripper(s), outline() * s, poses, weights), reference)


def test_the_contact_band_is_a_length_the_caller_scales(reference) -> None:
    """Left at its 0.25 mm in a scene 2.5 times larger, the band is relatively narrower: fewer
    stations count as touching, and some grasps lose their force closure."""
    s = 2.5
    poses = np.column_stack([POSES[:, :2] * s, POSES[:, 2]])
    unscaled = scored(gripper(s), outline() * s, poses)
    assert unscaled.force_closure.sum() < reference.force_closure.sum()


def test_force_closure_always_outranks_no_closure_whatever_the_weights() -> None:
    """Random ScoreWeights (every field within its range) on a grid about the object: every valid
    candidate in force closure scores above every valid candidate without."""
    rng = np.random.default_rng(30)
    xs, ys, angles = np.meshgrid(np.linspace(-8, 8, 5), np.linspace(-8, 14, 7), np.linspace(-0.2, 0.2, 3),
                                 indexing="ij")
    poses = np.stack([xs.ravel(), ys.ravel(), angles.ravel()], -1)
    for _ in range(6):
        weights = ScoreWeights(mu=rng.uniform(0.1, 1.5), tip_only=rng.uniform(), penetration=rng.uniform(),
                               event=rng.uniform(), touch=rng.uniform(0, 3), wrap=rng.uniform(0, 3),
                               opposition=rng.uniform(0.01, 3), contact_band=rng.uniform(0.05, 1.0),
                               max_penetration=rng.uniform(0.2, 1.0))
        result = scored(gripper(), outline(), poses, weights)
        closed = result.valid & result.force_closure
        open_ = result.valid & ~result.force_closure
        assert closed.sum() > 0 and open_.sum() > 0
        assert result.score[closed].min() > result.score[open_].max()
        assert result.score[closed].min() >= 1.0 and result.score[open_].max() <= 0.99
