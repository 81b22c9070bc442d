"""Candidate batches with NaN, inf, far-away, empty, single and large inputs.

Invalid candidates come back ``valid=False``, and a candidate's result does not depend on its
neighbours: it is compared, bit for bit, with the same candidate alone (a batch of copies of it,
so that both calls share one compiled function). Batch shapes are fixed so that nothing compiles
per example.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from softgrip_jax import FingerModel, Gripper, PolygonSDF, SDFGrid, SoftgripError, Status, estimate_batch, score
from softgrip_jax._batch import as_candidates
from softgrip_jax import Geometric

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=4)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=40.0)
# A disc of radius 8 mm at (30, 40) mm in a 120 x 100 mm grid from (-40, -30) mm.
GRID = SDFGrid.sample(PolygonSDF.regular((30.0, 40.0), 8.0, 32), origin=(-40.0, -30.0), spacing=(1.0, 1.0),
                      shape=(100, 120))
B = 16  # every fuzzed batch has this many candidates

#: Coordinates (mm) that make a candidate invalid: not finite, or far outside the grid (the image).
POISON_MM = st.sampled_from([np.nan, np.inf, -np.inf, 1e6, -1e6, 3e38, -3e38])
#: Angles (rad) that make a pose invalid: any finite angle is a rotation.
POISON_RAD = st.sampled_from([np.nan, np.inf, -np.inf])
MM = st.floats(-30.0, 60.0, width=32)
RAD = st.floats(-0.5, 0.5, width=32)


def batches(columns):
    """(candidates (B, len(columns)) float32, poisoned (B,) bool): random usable candidates around the
    disc, some of whose values are replaced by poison. ``columns``: (usable, poison) strategies."""
    row = st.tuples(*(usable for usable, _ in columns))
    cells = st.tuples(*(st.one_of(st.none(), poison) for _, poison in columns))  # None: keep the usable value
    return st.tuples(st.lists(row, min_size=B, max_size=B), st.lists(cells, min_size=B, max_size=B)).map(_poison)


def _poison(drawn):
    rows, cells = drawn
    x = np.array(rows, np.float32)
    mask = np.array([[c is not None for c in r] for r in cells])
    x[mask] = np.array([c for r in cells for c in r if c is not None], np.float32)
    return x, mask.any(axis=1)


def touching_first(usable: np.ndarray, case) -> np.ndarray:
    """Indices of the usable candidates, those whose fingers touch the object (case > 0) first."""
    index = np.flatnonzero(usable)
    return index[np.argsort(-np.asarray(case)[index], kind="stable")]


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def assert_same_candidate(batch_out, i: int, alone_out) -> None:
    """Candidate i of ``batch_out`` equals candidate 0 of ``alone_out``, bit for bit (NaN == NaN)."""
    for a, b in zip(leaves(batch_out), leaves(alone_out)):
        np.testing.assert_array_equal(a[i], b[0])


@settings(max_examples=15, deadline=None)
@given(batches([(MM, POISON_MM)] * 2))
def test_estimate_batch_flags_poisoned_bases_and_isolates_the_others(drawn):
    bases, poisoned = drawn
    out = estimate_batch(FINGER, GRID, bases, estimator=Geometric())
    valid, status = np.asarray(out.valid), np.asarray(out.status)
    assert not valid[poisoned].any()
    assert set(status[poisoned]) <= {Status.NON_FINITE_INPUT, Status.BASE_OUTSIDE_SDF, Status.COORDINATE_OUT_OF_RANGE}
    assert np.isnan(np.asarray(out.joints)[poisoned]).all()
    for i in touching_first(~poisoned, out.case)[:3]:  # three per example keep it quick
        alone = estimate_batch(FINGER, GRID, np.repeat(bases[i:i + 1], B, axis=0), estimator=Geometric())
        assert_same_candidate(out, i, alone)


@pytest.mark.slow  # fifteen drawn batches of scores: about 60 s
@settings(max_examples=15, deadline=None)
@given(batches([(MM, POISON_MM)] * 2 + [(RAD, POISON_RAD)]))
def test_score_flags_poisoned_poses_and_isolates_the_others(drawn):
    poses, poisoned = drawn
    out = score(GRIPPER, GRID, poses)  # the default, mechanics estimate: solves gathered across candidates
    valid = np.asarray(out.valid)
    assert not valid[poisoned].any()
    assert np.isneginf(np.asarray(out.score)[~valid]).all()
    for finger in (out.grasp.left, out.grasp.right):
        assert np.isnan(np.asarray(finger.joints)[poisoned]).all()
    for i in touching_first(~poisoned, np.asarray(out.grasp.left.case) + np.asarray(out.grasp.right.case))[:3]:
        alone = score(GRIPPER, GRID, np.repeat(poses[i:i + 1], B, axis=0))
        assert_same_candidate(out, i, alone)


@pytest.mark.slow  # compiles every entry point for empty batches: about 35 s
def test_empty_batches_return_empty_results():
    est = estimate_batch(FINGER, GRID, np.zeros((0, 2), np.float32), estimator=Geometric())
    assert est.joints.shape == (0, FINGER.n_links + 1, 2) and est.valid.shape == (0,)
    scored = score(GRIPPER, GRID, np.zeros((0, 3), np.float32))
    assert scored.score.shape == (0,) and scored.valid.shape == (0,)
    assert scored.grasp.left.joints.shape == (0, FINGER.n_links + 1, 2)


def test_one_candidate_is_the_candidate_of_a_batch():
    base = np.array([[10.0, 5.0]], np.float32)  # up and left of the disc: the finger wraps it
    one = estimate_batch(FINGER, GRID, base, estimator=Geometric())
    many = estimate_batch(FINGER, GRID, np.repeat(base, B, axis=0), estimator=Geometric())
    assert one.valid.shape == (1,) and bool(one.valid[0]) and int(one.case[0]) != 0
    for a, b in zip(leaves(one), leaves(many)):
        np.testing.assert_allclose(a[0], b[0], atol=1e-5)


@pytest.mark.slow
def test_50k_bases_with_poisoned_ones_in_one_call():
    rng = np.random.default_rng(0)
    bases = rng.uniform([-30.0, -20.0], [60.0, 60.0], (50_000, 2)).astype(np.float32)
    bad = rng.choice(len(bases), 500, replace=False)
    bases[bad[:250], 0] = np.nan
    bases[bad[250:]] = 1e6
    out = estimate_batch(FINGER, GRID, bases, estimator=Geometric())
    valid = np.asarray(out.valid)
    assert valid.shape == (50_000,) and not valid[bad].any() and valid.sum() > 25_000
    assert np.isfinite(np.asarray(out.joints)[valid]).all()
    # A sample of the good candidates equals each alone (compared to the B-copies batch compiled above).
    for i in np.setdiff1d(np.arange(len(bases)), bad)[::5000]:
        alone = estimate_batch(FINGER, GRID, np.repeat(bases[i:i + 1], B, axis=0), estimator=Geometric())
        for a, b in zip(leaves(out), leaves(alone)):
            np.testing.assert_allclose(a[i], b[0], atol=1e-5)


@pytest.mark.filterwarnings("ignore:overflow encountered in cast")  # float64 beyond float32's range
@settings(max_examples=100, deadline=None)
@given(hnp.arrays(hnp.scalar_dtypes() | hnp.byte_string_dtypes() | hnp.unicode_string_dtypes(),
                  hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4)), st.sampled_from([2, 3]))
def test_a_batch_of_the_wrong_shape_or_dtype_is_a_softgrip_error(array, width):
    # estimate_batch, estimate_grasp_batch, score and refine read their candidates through as_candidates
    # (called directly: under pytest, jaxtyping checks the annotations before the function runs).
    try:
        out = as_candidates(array, width, np.float32, "poses")
    except SoftgripError as err:
        assert str(err).startswith(f"poses must be a (B, {width}) array of real numbers")
    else:
        assert array.ndim == 2 and array.shape[1] == width and array.dtype.kind in "iuf"
        assert out.shape == array.shape and out.dtype == np.float32
