"""Object masks to signed distances (softgrip_vision.object_sdf): zero level against the true outline on the
rendered scenes and on point-sampled and anti-aliased masks of tilted planes (no bias), distances
against geometry, the grid's shape, objects cut by the image border, bad masks."""

from __future__ import annotations

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.path import Path

from benchmarks.vision_accuracy import (
    REQUIREMENTS,
    accuracy_scenes,
    distance_to_outline,
    measure,
    sdf_lookup,
    zero_level_px,
)
from softgrip_jax import FAR_MM, SDFGrid
from softgrip_vision.frames import Intrinsics
from softgrip_vision.geometry import PlaneCamera
from softgrip_vision.object_sdf import ObjectMaskError, object_polygon, object_sdf
from softgrip_vision.segmentation import segment
from synthetic.render import LABEL_OBJECT, Scene, d405_intrinsics, mm_to_px, render, render_labels
from synthetic.scenes import gripper_centrelines
from synthetic.shapes import shape

INTR = d405_intrinsics()
PLANE_MM = 120.0
CAMERA = PlaneCamera(INTR, PLANE_MM)
WITH_OBJECT = [s for s in accuracy_scenes(20) if s.object_name is not None]


def lookup_px(grid, points_px: np.ndarray, camera: PlaneCamera = CAMERA) -> np.ndarray:
    """The grid's signed distance at pixel positions (P, 2), in px."""
    return np.asarray(sdf_lookup(grid, jnp.asarray(camera.px_to_mm(points_px)))) / camera.mm_per_px


def disc(centre_px: tuple[float, float], radius_px: float, shape_hw=(480, 640)) -> np.ndarray:
    v, u = np.indices(shape_hw)
    return np.hypot(u - centre_px[0], v - centre_px[1]) <= radius_px


# --- accuracy on the rendered scenes ----------------------------------------------------------


@pytest.mark.parametrize("scene", WITH_OBJECT, ids=lambda s: f"scene{s.index}-{s.object_name}")
def test_zero_level_lies_on_the_true_outline(scene) -> None:
    errors = measure(scene)
    assert errors.sdf_zero_level_px <= REQUIREMENTS["sdf_zero_level_px"]
    assert errors.sdf_outline_px <= 1.0  # and the outline on the zero level, away from sharp apexes
    assert errors.sdf_apex_px <= 2.0  # at apexes, no pixel centre may fall near the tip


def test_distances_are_euclidean_millimetres_negative_inside() -> None:
    centre, radius = (300.3, 210.6), 40.0
    grid = object_sdf(disc(centre, radius), CAMERA)
    assert grid.values.shape == (480, 640)
    assert np.allclose(np.asarray(grid.spacing), CAMERA.spacing_mm)
    assert np.allclose(np.asarray(grid.origin), CAMERA.origin_mm)
    probes = np.array([(centre[0] + 20.0, centre[1]), (centre[0], centre[1] - 39.0), (centre[0] - 30.0, centre[1]),
                       (centre[0] + 45.0, centre[1]), (centre[0] + 60.0, centre[1] + 80.0)])
    true = np.hypot(*(probes - centre).T) - radius
    assert np.allclose(lookup_px(grid, probes), true, atol=0.5)
    # On the medial axis (here the centre), interpolation between the samples cuts the distance's peak.
    assert lookup_px(grid, np.array([centre]))[0] == pytest.approx(-radius, abs=1.5)
    boundary = centre + radius * np.column_stack([np.cos(t := np.linspace(0, 2 * np.pi, 100)), np.sin(t)])
    assert np.abs(lookup_px(grid, boundary)).max() < 0.75


def test_grid_element_is_the_pixel_at_the_same_position() -> None:
    mask = np.zeros((480, 640), bool)
    mask[100:140, 200:260] = True
    grid = object_sdf(mask, CAMERA)
    values = np.asarray(grid.values)
    assert values[120, 230] < 0 < values[120, 300]
    assert np.array_equal(values < 0, mask)
    assert values[99, 230] == pytest.approx(0.5 * CAMERA.mm_per_px, rel=1e-5)  # half a pixel outside
    assert values[100, 230] == pytest.approx(-0.5 * CAMERA.mm_per_px, rel=1e-5)


def test_non_square_pixels_keep_positions_exact() -> None:
    tall = Intrinsics(width=640, height=480, fx=385.0, fy=392.0, ppx=321.6, ppy=238.9, depth_scale=1e-4)
    polygon = shape("pentagon", 40.0, 0.2) + (4.0, 6.0)
    scene = Scene(gripper_centrelines((0.0, -40.0), 70.0, 52.0), object_polygon=polygon)
    frame = render(scene, tall)
    seg = segment(frame)
    camera = PlaneCamera.from_frame(frame, seg.fingers)
    grid = object_sdf(seg.object, camera)
    assert np.allclose(np.asarray(grid.spacing), [PLANE_MM / 385.0, PLANE_MM / 392.0], rtol=1e-3)
    edges = np.roll(polygon, -1, axis=0) - polygon
    outline_mm = np.vstack([polygon + t * edges for t in np.linspace(0.0, 1.0, 40, endpoint=False)])
    assert np.abs(np.asarray(sdf_lookup(grid, jnp.asarray(outline_mm)))).max() < float(np.max(camera.spacing_mm))


# --- sub-pixel accuracy on any plane: masks sampled from the true outline ---------------------

GOAL_MM = 0.1  # the project's goal: mean |SDF| on the true outline, every object, tilts up to 10 degrees
BIAS_MM = 0.03  # the signed mean on the true outline: no outward or inward bias


def tilted(tilt_deg: float, depth_mm: float = PLANE_MM) -> PlaneCamera:
    """The plane at ``depth_mm`` on the axis, its normal ``tilt_deg`` from the axis (toward +x and +y)."""
    t, azimuth = math.radians(tilt_deg), 0.6
    return PlaneCamera(INTR, depth_mm, normal=(math.sin(t) * math.cos(azimuth), math.sin(t) * math.sin(azimuth),
                                              math.cos(t)))


def sampled_coverage(polygon_mm: np.ndarray, camera: PlaneCamera, k: int) -> np.ndarray:
    """(H, W) fraction of each pixel's k x k sub-pixel points (their rays hitting the plane) inside
    the polygon (V, 2) mm: k = 1 is a point-sampled mask (pixel centres), k = 4 an anti-aliased one."""
    outline_px = camera.mm_to_px(polygon_mm)
    u0, v0 = np.floor(outline_px.min(axis=0)).astype(int) - 2
    u1, v1 = np.ceil(outline_px.max(axis=0)).astype(int) + 2
    offsets = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(u0, u1)[:, None] + offsets).ravel()
    v = (np.arange(v0, v1)[:, None] + offsets).ravel()
    uu, vv = np.meshgrid(u, v)
    inside = Path(polygon_mm).contains_points(camera.px_to_mm(np.column_stack([uu.ravel(), vv.ravel()])))
    coverage = np.zeros((INTR.height, INTR.width))
    coverage[v0:v1, u0:u1] = inside.reshape(v1 - v0, k, u1 - u0, k).mean(axis=(1, 3))
    return coverage


def dense_outline(polygon_mm: np.ndarray, step_mm: float = 0.02) -> np.ndarray:
    """(P, 2) points every ``step_mm`` along the closed polygon (V, 2)."""
    ends = np.roll(polygon_mm, -1, axis=0)
    return np.vstack([a + np.linspace(0.0, 1.0, max(2, int(np.hypot(*(b - a)) / step_mm)), endpoint=False)[:, None]
                      * (b - a) for a, b in zip(polygon_mm, ends)])


def measured_sdf(polygon_mm: np.ndarray, camera: PlaneCamera, kind: str):
    coverage = sampled_coverage(polygon_mm, camera, 1 if kind == "hard" else 4)
    return object_sdf(coverage >= 0.5, camera, coverage=None if kind == "hard" else coverage)


OFFSETS_MM = [(0.137, -0.071), (-3.283, 2.459)]  # sub-pixel phases (1 px ~ 0.31 mm) and a shift
OBJECTS = {"square_20deg": shape("square", 20.0, math.radians(20.0)), "star_a": shape("star_a", 30.0, 0.3),
           "clover": shape("clover", 30.0, 0.3)}


@pytest.mark.parametrize("kind", ["hard", "coverage"])
@pytest.mark.parametrize("tilt_deg", [0.0, 8.0])
@pytest.mark.parametrize("offset_mm", OFFSETS_MM, ids=["phase", "shifted"])
@pytest.mark.parametrize("name", list(OBJECTS))
def test_zero_level_is_unbiased_on_the_true_outline(name: str, offset_mm, tilt_deg: float, kind: str) -> None:
    polygon = OBJECTS[name] + offset_mm
    camera = tilted(tilt_deg)
    on_outline = np.asarray(sdf_lookup(measured_sdf(polygon, camera, kind), jnp.asarray(dense_outline(polygon))))
    assert np.abs(on_outline).mean() <= GOAL_MM
    assert abs(on_outline.mean()) <= BIAS_MM


@pytest.mark.parametrize("kind", ["hard", "coverage"])
@pytest.mark.parametrize("tilt_deg", [0.0, 8.0])
@pytest.mark.parametrize("offset_mm", OFFSETS_MM, ids=["phase", "shifted"])
def test_circle_of_known_radius(offset_mm, tilt_deg: float, kind: str) -> None:
    radius, centre = 10.0, np.asarray(offset_mm)
    polygon = shape("circle", 2.0 * radius) + centre
    camera = tilted(tilt_deg)
    grid = measured_sdf(polygon, camera, kind)
    t = np.linspace(0.0, 2.0 * np.pi, 2000, endpoint=False)
    ring = np.column_stack([np.cos(t), np.sin(t)])
    on_circle = np.asarray(sdf_lookup(grid, jnp.asarray(centre + radius * ring)))
    # A hard mask's outline wavers by up to about 0.4 px along its staircase; the bicubic lookup
    # follows the samples' waver between them (0.052 mm mean here, 0.047 bilinearly).
    assert np.abs(on_circle).mean() <= (0.06 if kind == "hard" else 0.05)
    assert abs(on_circle.mean()) <= BIAS_MM
    # Euclidean millimetres in the plane, 1.5 mm (about 5 px) inside and outside. A hard mask's
    # outline wavers about the true one along its pixel staircase, and the distance to the nearest
    # waver reads about 0.04 mm short there; coverage's outline does not waver.
    for offset in (-1.5, 1.5):
        off_circle = np.asarray(sdf_lookup(grid, jnp.asarray(centre + (radius + offset) * ring)))
        assert np.abs(off_circle - offset).mean() <= (GOAL_MM if kind == "hard" else 0.05)
        assert abs((off_circle - offset).mean()) <= (GOAL_MM if kind == "hard" else BIAS_MM)
    # At the centre, the grid points of its cell are -R plus their distance from it, within 0.05 mm
    # with coverage. The lookup there is the bicubic lookup of the 4 x 4 grid points around the
    # cell across the cone's apex: that of their true values, up to the sum of the absolute
    # Catmull-Rom weights (at most 1.125 per axis) times the points' largest error, and between -R
    # and about 0.7 of a grid step above it. A hard mask places each point of its outline only
    # within half a pixel, and the centre, equally far from all of them, reads the nearest: within
    # half a pixel.
    tolerance = 0.05 if kind == "coverage" else 0.5 * camera.mm_per_px
    origin, spacing = np.asarray(grid.origin, float), np.asarray(grid.spacing, float)
    col, row = np.floor((centre - origin) / spacing).astype(int)
    rows, cols = np.meshgrid(np.arange(row - 1, row + 3), np.arange(col - 1, col + 3), indexing="ij")
    nodes = origin + np.stack([cols, rows], axis=-1) * spacing
    true = -radius + np.hypot(*(nodes - centre).transpose(2, 0, 1))
    error = np.abs(np.asarray(grid.values, float)[rows, cols] - true)
    assert error[1:3, 1:3].max() <= tolerance
    # the same lookup of the true values: a 4 x 4 grid whose middle cell holds the centre
    interpolated = float(SDFGrid(values=true, origin=nodes[0, 0], spacing=spacing).distance(np.asarray(centre)))
    at_centre = float(sdf_lookup(grid, jnp.asarray(centre)))
    assert at_centre == pytest.approx(interpolated, abs=1.125**2 * max(error.max(), tolerance))
    assert -radius - tolerance <= at_centre <= -radius + 0.75 * float(np.hypot(*spacing)) + tolerance

def test_grid_shape_depends_only_on_the_image_size() -> None:
    mask = np.zeros((480, 640), bool)
    mask[200:260, 300:370] = True
    shapes = {object_sdf(mask, tilted(tilt, depth)).values.shape for tilt in (0.0, 8.0) for depth in (110.0, 130.0)}
    assert shapes == {(480, 640)}


def test_tilted_grid_spans_the_whole_image() -> None:
    camera = tilted(8.0)
    grid = object_sdf(disc((320.0, 240.0), 40.0), camera)
    corners = camera.px_to_mm(np.array([[0.01, 0.01], [638.99, 0.01], [0.01, 478.99], [638.99, 478.99]]))
    assert bool(np.all(np.asarray(grid.contains(jnp.asarray(corners)))))
    assert np.all(np.asarray(sdf_lookup(grid, jnp.asarray(corners))) < 0.5 * FAR_MM)  # no corner reads far


def test_coverage_must_match_the_mask() -> None:
    mask = disc((320.0, 240.0), 20.0)
    with pytest.raises(ObjectMaskError, match="coverage.*shape"):
        object_sdf(mask, CAMERA, coverage=np.zeros((10, 10)))
    with pytest.raises(ObjectMaskError, match="coverage.*finite"):
        object_sdf(mask, CAMERA, coverage=np.full(mask.shape, np.nan))


def test_objects_a_pixel_across_and_coverage_without_an_outline() -> None:
    mask = np.zeros((480, 640), bool)
    mask[200, 300] = True  # a lone pixel shrinks in the smoothing but stays an object
    grid = object_sdf(mask, CAMERA)
    inside, near = lookup_px(grid, np.array([[300.0, 200.0], [303.0, 200.0]]))
    assert -0.5 <= inside < 0.0 and 2.5 <= near <= 3.0
    faint = mask * 0.6  # vanishes in the smoothing: traced unsmoothed
    assert lookup_px(object_sdf(mask, CAMERA, coverage=faint), np.array([[300.0, 200.0]]))[0] < 0.0
    disc_mask = disc((320.3, 240.6), 20.0)  # coverage nowhere above 1/2: the mask's outline
    hard = np.asarray(object_sdf(disc_mask, CAMERA).values)
    assert np.array_equal(np.asarray(object_sdf(disc_mask, CAMERA, coverage=np.zeros((480, 640))).values), hard)


# --- no object, objects at the border ---------------------------------------------------------


def test_no_object_reads_far_everywhere() -> None:
    grid = object_sdf(np.zeros((480, 640), bool), CAMERA)
    assert np.allclose(lookup_px(grid, np.array([[0.0, 0.0], [320.0, 240.0]])) * CAMERA.mm_per_px, FAR_MM)


def test_object_touching_the_image_border() -> None:
    # A circle whose centre lies on the left image edge: half of it is outside the image.
    radius_mm = 15.0
    centre_mm = CAMERA.px_to_mm([0.0, 300.0])
    outline = centre_mm + radius_mm * np.column_stack(
        [np.cos(t := np.linspace(0.0, 2.0 * np.pi, 192, endpoint=False)), np.sin(t)])
    scene = Scene(gripper_centrelines((10.0, -45.0), 60.0, 52.0), object_polygon=outline)
    frame = render(scene, INTR)
    seg = segment(frame)  # segmentation is unaffected
    labels = render_labels(scene, INTR)
    assert seg.object[:, 0].any() and (seg.object == (labels == LABEL_OBJECT)).mean() > 0.999
    camera = PlaneCamera.from_frame(frame, seg.fingers)
    grid = object_sdf(seg.object, camera)
    radius_px = radius_mm / camera.mm_per_px
    # The image border is not the boundary: at the border, the centre is a radius deep inside.
    assert lookup_px(grid, np.array([[0.0, 300.0]]), camera)[0] == pytest.approx(-radius_px, abs=0.5)
    # The visible boundary is where it should be...
    outline_px = mm_to_px(outline, INTR, PLANE_MM)
    assert distance_to_outline(zero_level_px(np.asarray(grid.values)), outline_px).max() < 1.0
    # ...and beyond the image the grid reads far: no contact with the unseen half.
    assert lookup_px(grid, np.array([[-5.0, 300.0]]), camera)[0] * camera.mm_per_px == pytest.approx(FAR_MM)
    # The polygon closes along the border.
    vertices = CAMERA.mm_to_px(np.asarray(object_polygon(seg.object, camera).vertices))
    assert vertices[:, 0].min() == pytest.approx(-0.375, abs=0.01)


# --- the contour polygon ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["star_a", "clover", "triangle_b", "crescent"])
def test_polygon_follows_the_true_outline(name: str) -> None:
    polygon_mm = shape(name, 30.0, 0.4) + (2.0, 7.0)
    scene = Scene(gripper_centrelines((0.0, -40.0), 60.0, 52.0), object_polygon=polygon_mm)
    seg = segment(render(scene, INTR))
    extracted = object_polygon(seg.object, CAMERA)
    vertices_px = CAMERA.mm_to_px(np.asarray(extracted.vertices))
    true_px = mm_to_px(polygon_mm, INTR, PLANE_MM)
    assert distance_to_outline(vertices_px, true_px).max() < 1.0
    area = cv2.contourArea(vertices_px.astype(np.float32))
    assert area == pytest.approx(cv2.contourArea(true_px.astype(np.float32)), rel=0.03)


def test_polygon_distance_is_signed_millimetres() -> None:
    centre, radius = (310.0, 220.0), 30.0
    polygon = object_polygon(disc(centre, radius), CAMERA)
    probes = CAMERA.px_to_mm(np.array([centre, (centre[0] + 50.0, centre[1])]))
    distance = jax.jit(lambda sdf, points: sdf.distance(points))  # one compilation, not one per operation
    assert np.allclose(np.asarray(distance(polygon, jnp.asarray(probes))) / CAMERA.mm_per_px, [-radius, 20.0],
                       atol=0.75)


def test_polygon_of_a_single_pixel() -> None:
    mask = np.zeros((480, 640), bool)
    mask[200, 300] = True
    vertices_px = CAMERA.mm_to_px(np.asarray(object_polygon(mask, CAMERA).vertices))
    assert len(vertices_px) >= 3
    assert np.abs(vertices_px - (300.0, 200.0)).max() <= 0.5


# --- bad masks --------------------------------------------------------------------------------


def test_mask_covering_the_whole_frame() -> None:
    with pytest.raises(ObjectMaskError, match="whole frame.*object_min_saturation"):
        object_sdf(np.ones((480, 640), bool), CAMERA)


@pytest.mark.parametrize("mask", [np.zeros(10, bool), np.zeros((1, 5), bool), np.zeros((4, 4, 3), bool)])
def test_mask_of_the_wrong_shape(mask: np.ndarray) -> None:
    with pytest.raises(ObjectMaskError, match="2-D"):
        object_sdf(mask, CAMERA)


def test_polygon_needs_an_object() -> None:
    with pytest.raises(ObjectMaskError, match="empty.*object_sdf handles"):
        object_polygon(np.zeros((480, 640), bool), CAMERA)
    with pytest.raises(ObjectMaskError, match="tolerance_px"):
        object_polygon(disc((300, 200), 10), CAMERA, tolerance_px=math.nan)
