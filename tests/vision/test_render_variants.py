"""The renderer's variants (what real set-ups have that a fronto-parallel flat finger does not):
a tilted gripper plane, round fingers, flat-cut bases, an object face nearer or farther than the
fingers, anti-aliased edges and uneven lighting.

Each is checked against something derived independently of the renderer's code: OpenCV's
``projectPoints`` for the tilted projection, the tangent rays of a cylinder for a round finger's
silhouette, the pinhole scale for a shifted object face, coverage areas for anti-aliasing.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from synthetic.render import (
    LABEL_FIRST_FINGER,
    LABEL_OBJECT,
    Scene,
    d405_intrinsics,
    plane_rotation,
    project,
    render,
    render_labels,
)
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import shape

INTR = d405_intrinsics()
R_MM = 4.0
QUIET = dict(n_depth_holes=0, color_noise_sigma=0.0, depth_noise_sigma_mm=0.0)


def _depth_mm(frame) -> np.ndarray:
    return frame.depth.astype(np.float64) * INTR.depth_scale * 1000.0


def _vertical_finger(x_mm: float, y0: float = -40.0, length: float = 52.0) -> np.ndarray:
    return np.column_stack([np.full(64, x_mm), np.linspace(y0, y0 + length, 64)])


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (8.0, 0.0), (0.0, -10.0), (6.0, 7.0)])
def test_projection_of_a_tilted_plane_is_opencvs(tilt):
    scene = Scene([], plane_depth_mm=118.0, tilt_deg=tilt)
    points = np.random.default_rng(0).uniform(-50.0, 50.0, size=(20, 2))
    rvec, _ = cv2.Rodrigues(plane_rotation(tilt))
    K = np.array([[INTR.fx, 0.0, INTR.ppx], [0.0, INTR.fy, INTR.ppy], [0.0, 0.0, 1.0]])
    expected, _ = cv2.projectPoints(np.column_stack([points, np.zeros(20)]), rvec, np.array([0.0, 0.0, 118.0]), K, None)
    np.testing.assert_allclose(project(scene, points, INTR), expected[:, 0], atol=1e-6)


@pytest.mark.parametrize("tilt", [(8.0, 0.0), (-5.0, 9.0)])
def test_tilted_plane_depth_reads_the_plane_where_each_ray_meets_it(tilt):
    scene = Scene([_vertical_finger(-20.0), _vertical_finger(20.0)], half_thickness=R_MM, tilt_deg=tilt, **QUIET)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    v, u = np.nonzero(labels >= LABEL_FIRST_FINGER)
    rays = np.column_stack([(u - INTR.ppx) / INTR.fx, (v - INTR.ppy) / INTR.fy, np.ones(u.size)])
    normal = plane_rotation(tilt)[:, 2]
    expected = 120.0 * normal[2] / (rays @ normal)  # z of the ray's meeting with n . p = n . (0, 0, 120)
    assert np.abs(_depth_mm(frame)[v, u] - expected).max() <= 0.051  # the 0.1 mm depth unit's rounding


def test_round_finger_silhouette_and_front_surface_are_a_cylinders():
    """A vertical round finger at x0: its outline in a row is where the tangent rays from the camera
    to the circle of radius r about (x0, Z) cross the row, and the depth the circle's front."""
    x0, z = 30.0, 120.0
    scene = Scene([_vertical_finger(x0, -30.0, 60.0)], half_thickness=R_MM, finger_section="round",
                  plane_depth_mm=z, **QUIET)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    row = int(round(INTR.ppy))  # the ray's y component is ~0 there: the cross-section is a circle
    cols = np.nonzero(labels[row] == LABEL_FIRST_FINGER)[0]
    phi, alpha = math.atan2(x0, z), math.asin(R_MM / math.hypot(x0, z))
    edges_px = INTR.fx * np.tan([phi - alpha, phi + alpha]) + INTR.ppx
    assert cols.min() == math.ceil(edges_px[0]) and cols.max() == math.floor(edges_px[1])
    # Wider than 2r at the plane depth (by 1/cos(phi)), as a real round finger looks off-axis.
    assert (edges_px[1] - edges_px[0]) * z / INTR.fx == pytest.approx(2 * R_MM / math.cos(phi), rel=2e-3)
    # Depth: the ray's first hit on the circle (x - x0)^2 + (z' - z)^2 = r^2.
    ray_x = (cols - INTR.ppx) / INTR.fx
    a, b, c = ray_x**2 + 1.0, -2.0 * (x0 * ray_x + z), x0**2 + z**2 - R_MM**2
    front = (-b - np.sqrt(np.maximum(b * b - 4 * a * c, 0.0))) / (2 * a)
    assert np.abs(_depth_mm(frame)[row, cols] - front).max() <= 0.06
    assert _depth_mm(frame)[row, cols].min() == pytest.approx(z - R_MM, abs=0.1)


@pytest.mark.parametrize("section", ["flat", "round"])
def test_flat_base_is_cut_square_and_rounded_base_is_capped(section):
    finger = _vertical_finger(0.0, -40.0)
    labels = {end: render_labels(Scene([finger], half_thickness=R_MM, finger_section=section, base_end=end, **QUIET),
                                 INTR)
              for end in ("rounded", "flat")}
    column = int(round(INTR.ppx))
    base_v = INTR.fy * -40.0 / 120.0 + INTR.ppy
    top = {end: np.nonzero(lab[:, column] == LABEL_FIRST_FINGER)[0].min() for end, lab in labels.items()}
    # The cut's nearest point: on the plane for a flat front, r in front of it for a round finger
    # (so, in perspective, a little farther from the image centre than the base itself).
    front_mm = 120.0 - (R_MM if section == "round" else 0.0)
    assert top["flat"] == math.ceil(INTR.fy * -40.0 / front_mm + INTR.ppy)
    cap_px = R_MM * INTR.fy / 120.0
    assert abs(top["rounded"] - (base_v - cap_px)) <= 1.0 + (0.5 if section == "round" else 0.0)
    below = labels["flat"][math.ceil(base_v) + 3]
    assert (below == LABEL_FIRST_FINGER).sum() == pytest.approx(2 * cap_px, abs=2.5)  # full width right away


@pytest.mark.parametrize("offset", [-3.0, 0.0, 3.0])
def test_object_outline_is_drawn_at_its_own_face_depth(offset):
    polygon = shape("square", 30.0, 0.3) + (2.0, 5.0)
    scene = Scene([], object_polygon=polygon, object_depth_offset_mm=offset, **QUIET)
    frame, labels = render(scene, INTR), render_labels(scene, INTR)
    area_px = (labels == LABEL_OBJECT).sum()
    expected = cv2.contourArea(project(scene, polygon, INTR, offset).astype(np.float32))
    assert area_px == pytest.approx(expected, rel=0.01)
    side_mm = float(np.sqrt(cv2.contourArea(polygon.astype(np.float32))))
    assert np.sqrt(area_px) == pytest.approx(side_mm * INTR.fx / (120.0 + offset), rel=0.01)
    assert np.median(_depth_mm(frame)[labels == LABEL_OBJECT]) == pytest.approx(120.0 + offset, abs=0.1)


def test_supersampled_colour_covers_each_edge_pixel_by_its_area():
    """Anti-aliased: a dark object on a uniform background; the colour at each pixel mixes the two
    in proportion to the area covered, so the summed coverage is the outline's area in px."""
    polygon = shape("circle", 24.0) + (1.3, 4.7)
    kwargs = dict(background_rgb=(0, 0, 0), object_rgb=(240, 0, 0), **QUIET)
    scene = Scene([], object_polygon=polygon, supersample=6, **kwargs)
    frame = render(scene, INTR)
    texture = render(Scene([], **kwargs), INTR).color[..., 0].astype(np.float64)  # background alone
    coverage = (frame.color[..., 0] - texture) / (240.0 - texture)
    edge = (coverage > 0.05) & (coverage < 0.95)
    assert edge.sum() > 100  # partial pixels all along the outline
    radius_px = 12.0 * INTR.fx / 120.0
    assert coverage.sum() == pytest.approx(math.pi * radius_px**2, rel=0.004)


def test_lighting_scales_the_colours_across_the_image():
    polygon = shape("rounded_rect", 200.0)  # fills the view
    flat = render(Scene([], object_polygon=polygon, **QUIET), INTR).color.astype(float)
    lit = render(Scene([], object_polygon=polygon, light_gain=0.8, light_gradient=0.4, **QUIET), INTR).color.astype(float)
    ratio = lit[240, :, 0] / flat[240, :, 0]
    assert ratio[0] == pytest.approx(0.8 * 0.8, abs=0.01) and ratio[-1] == pytest.approx(0.8 * 1.2, abs=0.01)


@pytest.mark.parametrize("field, value", [("tilt_deg", (80.0, 0.0)), ("tilt_deg", (1.0,)),
                                          ("finger_section", "oval"), ("base_end", "square"),
                                          ("supersample", 0), ("light_gain", 0.0)])
def test_bad_variant_is_named(field, value):
    with pytest.raises(ValueError, match=field):
        Scene(gripper_centrelines((0.0, -40.0), 60.0, 52.0), **{field: value})
