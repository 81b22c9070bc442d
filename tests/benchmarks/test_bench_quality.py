"""benchmarks/bench_quality.py's own reference (numpy wrenches, Qhull epsilon) against cases worked
out by hand, and its object outlines; nothing here compiles a score."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_quality as bench  # noqa: E402


@pytest.mark.parametrize("mu", [0.2, 0.5, 1.0])
def test_reference_epsilon_of_two_antipodal_contacts_is_the_hand_derived_one(mu) -> None:
    """Two antipodal contacts on a disc of radius rho about the centroid: the four edge wrenches
    (-+1, +-mu, +-mu) / sqrt(1 + mu^2) form a tetrahedron whose facets lie
    mu / sqrt((1 + mu^2)(2 + mu^2)) from the origin."""
    centre = np.array([4.0, 30.0])
    points = centre + [[12.0, 0.0], [-12.0, 0.0], [0.0, 12.0]]
    normals = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    touching = np.array([True, True, False])  # the third contact is left out
    wrenches = bench.reference_wrenches(points, normals, touching, mu, centre, 12.0)
    assert wrenches.shape == (4, 3)
    assert bench.reference_epsilon(wrenches) == pytest.approx(mu / math.sqrt((1 + mu**2) * (2 + mu**2)), rel=1e-9)


def test_reference_epsilon_is_zero_without_closure() -> None:
    normals = np.array([[1.0, 0.0], [-1.0, 0.0]])
    points = np.array([[10.0, 0.0], [-10.0, 0.0]])
    # One contact, a flat set and a frictionless pair: the origin is not strictly inside.
    assert bench.reference_epsilon(bench.reference_wrenches(points, normals, [True, False], 0.5, [0, 0], 10.0)) == 0.0
    assert bench.reference_epsilon(bench.reference_wrenches(points, normals, [True, True], 0.0, [0, 0], 10.0)) == 0.0
    # Both contacts pushing the same way (normals alike): no closure.
    same = np.array([[1.0, 0.0], [1.0, 0.0]])
    assert bench.reference_epsilon(bench.reference_wrenches(points, same, [True, True], 0.5, [0, 0], 10.0)) == 0.0


@pytest.mark.parametrize("name", bench.PAPER_OBJECTS + bench.CONCAVE_OBJECTS)
def test_resampled_outlines_keep_every_corner_and_the_area(name) -> None:
    outline = bench.object_outline(name)
    resampled = bench.resample_outline(outline, bench.VERTICES)
    assert resampled.shape == (bench.VERTICES, 2)
    kept = np.isclose(resampled[:, None, :], outline[None, :, :], atol=1e-12).all(-1).any(0)
    assert kept.all()

    def area(p):
        return 0.5 * abs(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))

    assert area(resampled) == pytest.approx(area(outline), rel=1e-12)


def test_pose_grid_covers_the_box_about_the_centred_pose() -> None:
    poses = bench.pose_grid(bench.centred_pose(), (5, 4, 3))
    assert poses.shape == (60, 3)
    np.testing.assert_allclose(poses.min(0), bench.centred_pose() + np.asarray(bench.BOX[0]), atol=1e-5)
    np.testing.assert_allclose(poses.max(0), bench.centred_pose() + np.asarray(bench.BOX[1]), atol=1e-5)
    assert len(bench.pose_grid(bench.centred_pose(), bench.SIZES["full"]["counts"])) >= 2000
    assert bench.centred_pose()[1] + bench.LENGTH_MM / 2 == bench.OBJECT_CENTRE_MM[1]
