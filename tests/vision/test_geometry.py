"""The tilted gripper plane (softgrip_vision.geometry): ray-plane mapping against hand-derived formulas, and the
plane fit against depth images computed here from the analytic surfaces (not the renderer's code).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from softgrip_vision.frames import Frame, FrameError
from softgrip_vision.geometry import PlaneCamera, face_offset_mm, fit_gripper_plane
from synthetic.render import d405_intrinsics

INTR = d405_intrinsics()


def normal_of(a_deg: float, b_deg: float) -> np.ndarray:
    """The normal of a plane turned by a about the camera's x axis, then by b about its y axis."""
    a, b = math.radians(a_deg), math.radians(b_deg)
    return np.array([math.cos(a) * math.sin(b), -math.sin(a), math.cos(a) * math.cos(b)])


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (10.0, 0.0), (0.0, -8.0), (7.0, 7.0)])
@pytest.mark.parametrize("offset", [0.0, -3.0, 2.5])
def test_pixels_map_to_the_point_their_ray_hits(tilt, offset) -> None:
    n = normal_of(*tilt)
    camera = PlaneCamera(INTR, 120.0, tuple(n), offset)
    uv = np.array([[10.0, 20.0], [321.6, 238.9], [600.0, 450.0]])
    # By hand: the ray t (u', v', 1) meets n . P = 120 n_z + offset at t = (120 n_z + offset) / (n . ray).
    rays = np.column_stack([(uv[:, 0] - INTR.ppx) / INTR.fx, (uv[:, 1] - INTR.ppy) / INTR.fy, np.ones(3)])
    t = (120.0 * n[2] + offset) / (rays @ n)
    np.testing.assert_allclose(camera.depth_at(uv), t)
    points = rays * t[:, None]
    np.testing.assert_allclose(camera.points_3d(camera.px_to_mm(uv)), points, atol=1e-9)
    np.testing.assert_allclose(camera.mm_to_px(camera.px_to_mm(uv)), uv, atol=1e-9)
    assert camera.tilt_deg == pytest.approx(math.degrees(math.acos(n[2])))


def test_parallel_planes_share_coordinates_by_orthogonal_projection() -> None:
    camera = PlaneCamera(INTR, 120.0, tuple(normal_of(8.0, -5.0)))
    face = camera.parallel(-4.0)  # 4 mm nearer the camera
    xy = np.array([[3.0, -7.0], [20.0, 30.0]])
    lifted, on_plane = face.points_3d(xy), camera.points_3d(xy)
    np.testing.assert_allclose(lifted - on_plane, -4.0 * np.asarray(camera.normal)[None].repeat(2, 0), atol=1e-9)
    # A pixel sees different plane coordinates on the two planes, unless it looks along the normal.
    uv = face.mm_to_px(xy)
    assert np.abs(camera.px_to_mm(uv) - xy).max() > 0.1
    np.testing.assert_allclose(face.px_to_mm(uv), xy, atol=1e-9)


def test_a_plane_facing_the_camera_is_the_pinhole_formula() -> None:
    camera = PlaneCamera(INTR, 120.0, offset_mm=3.0)
    uv = np.array([[400.0, 100.0]])
    np.testing.assert_allclose(camera.px_to_mm(uv), [[(400.0 - INTR.ppx) * 123.0 / INTR.fx,
                                                      (100.0 - INTR.ppy) * 123.0 / INTR.fy]])
    assert camera.faces_camera and camera.spacing_mm[0] == pytest.approx(123.0 / INTR.fx)
    # the local scale of a tilted plane grows where the plane is farther from the camera
    tilted = PlaneCamera(INTR, 120.0, tuple(normal_of(0.0, 10.0)))
    sides = np.array([[50.0, 240.0], [600.0, 240.0]])
    scale, depth = tilted.local_mm_per_px(sides), tilted.depth_at(sides)
    assert (scale[0] - scale[1]) * (depth[0] - depth[1]) > 0  # farther, larger pixels
    # at the principal point the footprint is Z / f tall and Z / (f cos b) wide
    centre = tilted.local_mm_per_px(np.array([INTR.ppx, INTR.ppy]))
    assert centre == pytest.approx(120.0 / INTR.fx / math.sqrt(math.cos(math.radians(10.0))), rel=1e-4)


@pytest.mark.parametrize("normal", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (np.nan, 0.0, 1.0)])
def test_bad_normals_are_refused(normal) -> None:
    with pytest.raises(FrameError, match="normal"):
        PlaneCamera(INTR, 120.0, normal)


def fingers_frame(tilt: tuple[float, float], relief_mm: float, *, noise_mm: float = 0.0, seed: int = 0,
                  object_offset: float | None = None) -> tuple[Frame, list[np.ndarray], float]:
    """Two straight vertical fingers (half-width 4 mm, in plane coordinates x = -30 and +30, y from -40
    to 12) on a plane through (0, 0, 120) with the given tilt, seen by a D405. With ``relief_mm`` 0 a
    finger is a flat strip on the plane; otherwise a tube of radius 4 mm about its centreline whose
    front is ``relief_mm`` nearer (4: round), ray-cast: each pixel reads where its ray enters the
    tube (an elliptic cylinder), and the mask is the tube's outline. An optional 20 mm square object
    face at ``object_offset``. Returns the frame, the finger masks and r in px."""
    camera = PlaneCamera(INTR, 120.0, tuple(normal_of(*tilt)))
    v, u = np.indices((INTR.height, INTR.width), dtype=np.float64)
    uv = np.stack([u, v], -1)
    depth = np.full(u.shape, 400.0)
    masks = []
    r = 4.0
    xy = camera.px_to_mm(uv)
    n = np.asarray(camera.normal)
    rays = camera.rays(uv)
    ex, ey, _ = camera.axes
    for centre in (-30.0, 30.0):
        if relief_mm == 0.0:
            mask = (np.abs(xy[..., 0] - centre) <= r) & (xy[..., 1] >= -40.0) & (xy[..., 1] <= 12.0)
            surface = camera.depth_at(uv)
        else:
            # Scale the normal direction by r / relief so the elliptic tube becomes a circular one.
            origin = camera.points_3d(np.array([centre, 0.0]))
            stretch = lambda w: w + (r / relief_mm - 1.0) * (w @ n)[..., None] * n  # noqa: E731
            d, a = stretch(rays), stretch(-origin)
            d_perp, a_perp = d - (d @ ey)[..., None] * ey, a - (a @ ey) * ey
            qa, qb, qc = (d_perp**2).sum(-1), (d_perp * a_perp).sum(-1), a_perp @ a_perp - r**2
            disc = qb**2 - qa * qc
            t = (-qb - np.sqrt(np.clip(disc, 0.0, None))) / qa
            along = (t[..., None] * rays - origin) @ ey
            mask = (disc >= 0.0) & (along >= -40.0) & (along <= 12.0)
            surface = t  # rays have z = 1
        depth[mask] = surface[mask]
        masks.append(mask)
    if object_offset is not None:
        face = camera.parallel(object_offset)
        oxy = face.px_to_mm(uv)
        square = (np.abs(oxy[..., 0]) <= 10.0) & (np.abs(oxy[..., 1] - 20.0) <= 10.0)
        depth[square] = face.depth_at(uv)[square]
    depth += noise_mm * np.random.default_rng(seed).standard_normal(depth.shape)
    raw = np.clip(np.rint(depth / (INTR.depth_scale * 1000.0)), 1, 65535).astype(np.uint16)
    frame = Frame(color=np.zeros((INTR.height, INTR.width, 3), np.uint8), depth=raw, intrinsics=INTR)
    return frame, masks, r / camera.local_mm_per_px(np.array([320.0, 240.0]))


def centrelines(tilt: tuple[float, float]) -> list[np.ndarray]:
    """The fingers' true centrelines of :func:`fingers_frame` in px."""
    camera = PlaneCamera(INTR, 120.0, tuple(normal_of(*tilt)))
    y = np.linspace(-40.0, 12.0, 100)
    return [camera.mm_to_px(np.column_stack([np.full_like(y, x), y])) for x in (-30.0, 30.0)]


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (10.0, 0.0), (-6.0, 8.0)])
@pytest.mark.parametrize("relief", [0.0, 4.0])
def test_the_plane_fit_recovers_tilt_depth_and_relief(tilt, relief) -> None:
    frame, masks, r_px = fingers_frame(tilt, relief, noise_mm=0.2)
    fit = fit_gripper_plane(frame, masks, [r_px, r_px], centrelines_px=centrelines(tilt),
                            width_edges_px=width_edges(tilt, relief))
    n = normal_of(*tilt)
    assert math.degrees(math.acos(np.clip(np.asarray(fit.camera.normal) @ n, -1, 1))) < 0.15
    # the plane's depth on the optical axis: 120 / ... = 120 exactly (the plane passes through (0, 0, 120));
    # behind a round finger's front the plane is the bulge's extrapolation to its edge, where readings
    # are few and steep: 0.2 mm (0.17 % of the millimetre) for a 4 mm relief
    assert fit.camera.depth_mm == pytest.approx(120.0, abs=0.1 if relief == 0.0 else 0.2)
    assert fit.relief_mm == pytest.approx([relief, relief], abs=0.25)
    assert fit.relief_measured


def test_a_given_relief_is_used_and_the_median_is_not() -> None:
    frame, masks, r_px = fingers_frame((0.0, 0.0), 4.0)
    given = fit_gripper_plane(frame, masks, [r_px, r_px], relief_mm=4.0)  # the bulge in pixels: within 0.1 mm
    assert given.camera.depth_mm == pytest.approx(120.0, abs=0.1) and not given.relief_measured
    # the median front-surface reading lies about pi/4 r nearer: the millimetres it gives are 2.6 % short
    median = PlaneCamera.from_frame(frame, masks[0] | masks[1])
    assert 120.0 - median.depth_mm == pytest.approx(math.pi / 4 * 4.0, abs=0.4)


@pytest.mark.parametrize("offset", [-3.0, 3.0])
def test_the_object_face_offset(offset) -> None:
    frame, masks, r_px = fingers_frame((8.0, 0.0), 0.0, object_offset=offset)
    fit = fit_gripper_plane(frame, masks, [r_px, r_px])
    obj = frame.depth < 3000  # everything nearer than the background
    obj &= ~(masks[0] | masks[1])
    assert face_offset_mm(frame, obj, fit.camera) == pytest.approx(offset, abs=0.1)


def test_too_few_readings() -> None:
    frame, masks, r_px = fingers_frame((0.0, 0.0), 0.0)
    depth = frame.depth.copy()
    depth[masks[0] | masks[1]] = 0
    with pytest.raises(FrameError, match="no depth reading in finger region 0"):
        fit_gripper_plane(Frame(frame.color, depth, frame.intrinsics), masks, [r_px, r_px])


def width_edges(tilt: tuple[float, float], relief: float = 0.0) -> list[np.ndarray]:
    """(S, 2, 2) the true side points (px) across each finger of :func:`fingers_frame`: the outline,
    r from the centreline in the plane for a flat strip, r / cos(beta) for a round tube seen at
    an angle beta across its axis (its tangent rays)."""
    camera = PlaneCamera(INTR, 120.0, tuple(normal_of(*tilt)))
    ex = camera.axes[0]
    y = np.linspace(-36.0, 8.0, 40)
    out = []
    for x in (-30.0, 30.0):
        axis = camera.points_3d(np.column_stack([np.full_like(y, x), y]))
        sin_beta = (axis / np.linalg.norm(axis, axis=1, keepdims=True)) @ ex
        half = 4.0 / np.sqrt(1.0 - sin_beta**2) if relief > 0.0 else np.full_like(y, 4.0)
        out.append(np.stack([camera.mm_to_px(np.column_stack([x + side * half, y])) for side in (-1.0, 1.0)], axis=1))
    return out
