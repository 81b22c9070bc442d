"""The paper's pixel procedure (benchmarks/paper_pixel.py) against geometry worked out by hand and
against the JAX estimate, and its harness (benchmarks/bench_paper_speed.py) on its tiny configuration."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_paper_speed as bench  # noqa: E402
import paper_pixel as pp  # noqa: E402

from softgrip_jax import FingerModel, pcc_joints  # noqa: E402

PX = 0.1  # mm per pixel


def closed_form_pcc(length, theta, n, base=(0.0, 0.0), psi=0.0):
    """Eq. 2 by hand: joint i at chord angle psi + Theta i / N, (L/N) sin(Theta i/N) / sin(Theta/N) away."""
    i = np.arange(n + 1)
    chord = (length / n) * np.sin(theta * i / n) / np.sin(theta / n) if theta > 0 else length * i / n
    angle = psi + theta * i / n
    return np.asarray(base) + np.stack([chord * np.sin(angle), chord * np.cos(angle)], axis=-1)


def test_no_object_is_case_a_with_the_pcc_joints():
    finger = pp.PixelFinger(52.0, 0.5, 4.0, 10)
    base = np.array([3.2, -1.7])
    raster = pp.Raster.covering(base - 60.0, base + 60.0, PX)
    est = pp.PixelScene.from_mask(np.zeros(raster.shape, np.uint8), raster).estimate(finger, base)
    assert est.case == pp.NONE and not est.touches
    expected = closed_form_pcc(52.0, 0.5, 10, base)
    np.testing.assert_allclose(est.joints, expected, atol=1e-9)
    np.testing.assert_allclose(est.joints, pcc_joints(FingerModel(52.0, 0.5, 4.0, 10), jnp.asarray(base)), atol=1e-4)
    # An object out of reach is no different.
    far = np.array([[200.0, 0.0], [230.0, 0.0], [230.0, 30.0], [200.0, 30.0]])
    assert pp.estimate(far, base, finger, PX).case == pp.NONE


@pytest.mark.parametrize("n", [2, 10, 20])
def test_wall_is_first_touched_by_the_tip_at_the_hand_computed_angle(n):
    """A wall x = x_w right of the finger. The PCC chain's tip is its rightmost point (eq. 2: chord
    (L/N) sin s / sin(s/N) at angle s), so the rounded tip touches first, when x_tip(s) + r = x_w:
    case (b) with Theta_o1 = s1, and the free arc turned back about the base by Theta - s1."""
    length, theta, r, x_wall = 52.0, 0.5, 4.0, 16.0
    x_tip = lambda s: (length / n) * math.sin(s) / math.sin(s / n) * math.sin(s)
    lo, hi = 1e-6, theta
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if x_tip(mid) + r < x_wall else (lo, mid)
    s1 = 0.5 * (lo + hi)
    wall = np.array([[x_wall, -20.0], [x_wall + 30.0, -20.0], [x_wall + 30.0, 80.0], [x_wall, 80.0]])
    est = pp.estimate(wall, (0.0, 0.0), pp.PixelFinger(length, theta, r, n), PX)

    pixel_angle = PX / ((x_tip(s1 + 1e-4) - x_tip(s1 - 1e-4)) / 2e-4)  # one pixel of tip travel (rad)
    assert est.case == pp.TIP
    assert est.s1 == pytest.approx(s1, abs=1.5 * pixel_angle)
    assert est.l_g1 == pytest.approx(length) and est.n_g1 == pytest.approx(n)  # eqs. 6-7 at the tip
    assert est.theta_o1 == pytest.approx(s1, abs=1.5 * pixel_angle)  # the tip's chord angle
    expected = closed_form_pcc(length, theta, n, psi=-(theta - s1))  # eqs. 8-9, Fig. 10
    np.testing.assert_allclose(est.joints, expected, atol=length * 1.5 * pixel_angle)


@pytest.mark.parametrize("center, radius", [((14.0, 30.0), 6.0), ((20.0, 25.0), 10.0)])
def test_rigid_sweep_touches_a_circle_where_the_finger_is_tangent(center, radius):
    """The straight finger rotating about its base touches a circle when its line is at distance
    R + r from the centre: s1 = acos((R + r) / rho) - phi0; the contact is the centre's foot."""
    r, length = 3.0, 50.0
    cx, cy = center
    rho, phi0 = math.hypot(cx, cy), math.atan2(cy, cx)
    s1 = math.acos((radius + r) / rho) - phi0
    u = np.array([math.sin(s1), math.cos(s1)])
    foot = (cx * u[0] + cy * u[1]) * u
    t = np.linspace(0.0, 2.0 * math.pi, 720, endpoint=False)
    circle = np.asarray(center) + radius * np.stack([np.cos(t), np.sin(t)], axis=-1)
    est = pp.estimate(circle, (0.0, 0.0), pp.PixelFinger(length, 0.9, r, 10), PX, sweep="rigid")

    pixel_angle = PX / np.linalg.norm(foot)
    assert est.touches and not est.initial_overlap
    assert est.s1 == pytest.approx(s1, abs=1.5 * pixel_angle)
    assert est.theta_o1 == pytest.approx(s1, abs=1.5 * pixel_angle)  # P_g1 lies on the finger's line
    # Along a smooth surface the first overlapping pixels can sit anywhere where the gap is within
    # a fraction of a pixel of its minimum: about sqrt(2 (R + r) px) either way.
    np.testing.assert_allclose(est.p_g1, foot, atol=math.sqrt(2 * (radius + r) * PX))
    assert est.l_g1 == pytest.approx(np.linalg.norm(foot), abs=math.sqrt(2 * (radius + r) * PX))


def test_case_d_splits_the_links_at_the_fractional_contact_link():
    finger = pp.PixelFinger(50.0, 0.6, 4.0, 4)
    joints = pp.deformed_joints(pp.OTHER, finger, (0.0, 0.0), theta_o1=0.2, n_g1=2.5)
    # Links 0, 1: 2 * 0.2 / 2.5 each; link 2 half and half; link 3: 2 * 0.4 / 1.5.
    first, rest = 0.4 / 2.5, 0.8 / 1.5
    turning = np.array([first, first, 0.5 * (first + rest), rest])
    np.testing.assert_allclose(joints, pp.chain_joints((0.0, 0.0), 0.0, turning, 50.0), atol=1e-12)
    # The first N_g1 links end on the chord at Theta_o1 when N_g1 is whole.
    whole = pp.deformed_joints(pp.OTHER, finger, (0.0, 0.0), theta_o1=0.2, n_g1=2.0)
    assert math.atan2(*whole[2]) == pytest.approx(0.2, abs=1e-12)


@pytest.fixture(scope="module")
def handful():
    """Two scenes of each case (by the JAX estimate) from the harness's scene set, N = 10."""
    scenes = bench.faithfulness_scenes(40)
    case, joints, valid = bench.jax_scene_estimates(scenes, 10)
    picked = [i for c in range(4) for i in np.nonzero((case == c) & valid)[0][:2]]
    return [(scenes[i], int(case[i]), joints[i]) for i in picked]


def test_reference_agrees_with_the_jax_estimate_on_a_handful_of_scenes(handful):
    assert sorted({c for _, c, _ in handful}) == [0, 1, 2, 3]
    for scene, case, joints in handful:
        finger = pp.PixelFinger(scene.length, scene.theta, scene.half_thickness, 10)
        est = pp.estimate(scene.polygon, scene.base, finger, PX)
        assert est.case == case, scene.object_name
        assert np.linalg.norm(est.joints - joints, axis=-1).max() < 1.0, scene.object_name


@pytest.mark.slow
def test_quick_harness_runs_end_to_end_and_writes_its_outputs(tmp_path, capsys):
    report = bench.main(["--quick", "--out", str(tmp_path)])
    png, raw = tmp_path / "paper_speed.png", tmp_path / "paper_speed.json"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = json.loads(raw.read_text())
    assert saved["config"]["quick"] and saved["faithfulness"] and saved["timed_agreement"]
    rows = {(r["n_links"], r["batch"]): r for r in saved["speed"]}
    assert set(rows) == {(2, 1), (2, 4)}
    assert rows[(2, 4)]["reference_extrapolated_from"] == 2  # timed on 2 candidates, extrapolated to 4
    assert all(r["ratio"] > 0 and r["jax_per_s"] > 0 for r in rows.values())
    assert report["config"] == saved["config"]
    printed = capsys.readouterr().out
    assert "| N | batch |" in printed and "cases agree" in printed
