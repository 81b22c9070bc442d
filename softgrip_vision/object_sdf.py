"""Object mask -> signed distance in millimetres, as the core's ``SDFGrid`` or ``PolygonSDF``.

**The zero level.** A mask (or a colour coverage image, below) is a function sampled at pixel
centres. The object's outline is taken as the 0.5 level of that function, smoothed by a Gaussian
of ``_SMOOTH_PX`` = 0.5 px (OpenCV), and found at sub-pixel precision by marching squares: linear
interpolation between each pair of neighbouring pixel centres on either side of the level, joined
into segments cell by cell. For a hard mask (0 or 1 per pixel) a straight edge along the pixel grid
then lies exactly halfway between the last pixel centre inside and the first outside, and a
slanted or curved edge on the average of its pixel staircase, not on its outer corners: unbiased.
The smoothing damps the staircase's one-pixel steps (their fundamental by exp(-2 pi^2 sigma^2) ~
0.007) and rounds a right-angled corner by 0.4 px. A hard mask still places each point of a
shallow edge only within half a pixel (its steps are longer than the smoothing): unbiased on
average, but the outline wavers by up to about 0.4 px, and distances a few pixels off it read the
nearest waver, on average about 0.1 px short. With a **coverage** image (each edge pixel's covered
fraction, :func:`softgrip_vision.coverage.edge_coverage`) the 0.5 level follows an anti-aliased edge to a
few hundredths of a pixel. Features about a pixel wide shrink in the smoothing (a lone pixel to
under half its width); an object that vanishes entirely (a faint coverage) is traced unsmoothed.

**The distance.** The outline's segments are mapped to millimetres in the plane by the camera's
ray-plane intersection (:meth:`PlaneCamera.px_to_mm`), so a tilted plane's perspective is exact,
and the grid holds the Euclidean distance (mm) in the plane from each grid point to them: exactly
(nearest segment among those of the nearest sample points, scipy's k-d tree) within
``_EXACT_BAND_PX`` = 8 px of the outline, where fingers touch; farther out, the distance to the
segment holding the closest point of the nearest grid point next to the outline (scipy's Euclidean
feature transform), which over-estimates by up to about one grid step (a small fraction of one on
average). The sign is the smoothed level's (negative inside).

**The grid.** Always (H, W), the image's size, whatever the plane's depth and tilt, so the frames of
one camera share one compilation downstream. It is the regular millimetre grid spanning the box
around the image's footprint in the plane (the plane points of its four corner pixel centres): for
a plane facing the camera, grid element (row v, column u) is pixel (u, v), origin pixel (0, 0)'s
position and spacing the pixel size (Z / fx, Z / fy). A tilted plane's footprint is a
quadrilateral: grid points outside it get distances to the visible outline extended straight past
the image border.

**Objects cut by the image border.** The part outside the image is unknown. The image border is
not treated as the object's boundary: inside the image, distances are to the visible boundary
only (an object pixel at the border has a negative value), and outside the grid the core reads
``SDFGrid.far``, i.e. never in contact. Contacts predicted near the border are therefore only as
good as the visible part of the object.

Example:
    >>> import numpy as np
    >>> from synthetic.render import d405_intrinsics
    >>> from softgrip_vision.geometry import PlaneCamera
    >>> mask = np.zeros((480, 640), bool); mask[200:260, 300:360] = True
    >>> grid = object_sdf(mask, PlaneCamera(d405_intrinsics(), 120.0))
    >>> grid.values.shape
    (480, 640)
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from softgrip_jax import FAR_MM, PolygonSDF, SDFGrid, SoftgripError
from softgrip_vision.geometry import PlaneCamera

_POLYGON_UPSAMPLE = 4
_SMOOTH_PX = 0.5  # Gaussian sigma (px) smoothing the mask's staircase before its 0.5 level is traced
_EXACT_BAND_PX = 8.0  # distances within this many pixels of the outline are exact
_SAMPLES_PER_SEGMENT = 4  # points per outline segment (<= 1.5 px long) in the k-d tree
_NEAREST_SAMPLES = 8  # the segments of this many nearest sample points are measured exactly


class ObjectMaskError(SoftgripError):
    """An object mask that cannot be turned into a signed-distance function."""


def object_sdf(mask: np.ndarray, camera: PlaneCamera, coverage: np.ndarray | None = None) -> SDFGrid:
    """Signed distance (mm, negative inside) to the object in ``mask``, on an (H, W) grid.

    Args:
        mask: (H, W) bool, the object's pixels (several components are one object).
        camera: the plane's camera (pixels <-> mm, tilted or not).
        coverage: (H, W) float in [0, 1], the fraction of each pixel the object covers (e.g.
            ``softgrip_vision.coverage.edge_coverage(frame.color, mask)``), or None for the hard mask. Its
            0.5 level (smoothed) is then the outline, to sub-pixel precision on anti-aliased edges;
            the mask only says whether there is an object (and is the outline where the coverage
            has no pixel on one side of 1/2).

    Returns:
        ``SDFGrid`` with values (H, W) in mm, origin (2,) mm and spacing (2,) mm of the regular
        grid spanning the image's footprint in the plane (module docstring); for a plane facing
        the camera, origin = pixel (0, 0) in mm and spacing = (Z / fx, Z / fy) mm. An empty mask
        (no object) gives a grid that reads ``FAR_MM`` everywhere: nothing can be touched (contact
        case (a)).

    Example (a 60 x 60 px square; at 120 mm one pixel is 120 / 385 mm):
        >>> import numpy as np
        >>> from synthetic.render import d405_intrinsics
        >>> camera = PlaneCamera(d405_intrinsics(), 120.0)
        >>> mask = np.zeros((480, 640), bool); mask[200:260, 300:360] = True
        >>> grid = object_sdf(mask, camera)
        >>> point = camera.px_to_mm(np.array([310.0, 229.5]))  # mm; the left edge is at u = 299.5
        >>> round(float(grid.distance(jnp.asarray(point))) / camera.mm_per_px, 2)  # 10.5 px inside
        -10.5
        >>> tilted = PlaneCamera(d405_intrinsics(), 130.0, normal=(0.1, 0.05, 1.0))  # about 6 degrees
        >>> object_sdf(mask, tilted).values.shape  # the image's size, whatever the plane
        (480, 640)

    Raises:
        ObjectMaskError: the mask is not 2-D or is smaller than 2x2, or covers the whole frame
            (no boundary: check the object's colour thresholds and the background cut-off), or the
            coverage does not match it.
    """
    inside = _as_mask(mask)
    origin, spacing = _grid_geometry(camera, inside.shape)
    values: np.ndarray | jax.Array
    if not inside.any():
        values = np.full(inside.shape, FAR_MM, dtype=np.float64)
    elif inside.all():
        raise ObjectMaskError("the object mask covers the whole frame, so it has no boundary: check "
                              "object_min_saturation and background_depth_mm of the segmentation")
    else:
        values = _signed_distance(_level(inside, coverage), camera, origin, spacing)
    dtype = jnp.result_type(float)
    return SDFGrid(values=jnp.asarray(values, dtype), origin=jnp.asarray(origin, dtype),
                   spacing=jnp.asarray(spacing, dtype))


def _grid_geometry(camera: PlaneCamera, shape_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Origin (2,) and spacing (2,) in mm of the (H, W) grid spanning the image's footprint."""
    h, w = shape_hw
    if camera.faces_camera:
        return camera.origin_mm, camera.spacing_mm
    corners = camera.px_to_mm(np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]]))
    low, high = corners.min(axis=0), corners.max(axis=0)
    return low, (high - low) / np.array([w - 1.0, h - 1.0])


def _level(inside: np.ndarray, coverage: np.ndarray | None) -> np.ndarray:
    """(H, W) float32: the smoothed coverage (the mask without one) minus 1/2; > 0 inside."""
    if coverage is None:
        level = inside.astype(np.float32)
    else:
        level = np.asarray(coverage, dtype=np.float32)
        if level.shape != inside.shape:
            raise ObjectMaskError(f"the coverage image must have the mask's shape {inside.shape}, got "
                                  f"{level.shape}")
        if not np.isfinite(level).all():
            raise ObjectMaskError("the coverage image must be finite (fractions in [0, 1])")
        level = np.clip(level, 0.0, 1.0)
        if not ((level > 0.5).any() and (level <= 0.5).any()):  # no outline in the coverage: the mask's
            level = inside.astype(np.float32)
    smooth = cv2.GaussianBlur(level, (0, 0), _SMOOTH_PX, borderType=cv2.BORDER_REPLICATE) - 0.5
    if (smooth > 0).any() and (smooth <= 0).any():
        return smooth
    return level - 0.5  # an object that vanishes in the smoothing (a faint coverage): unsmoothed


def _signed_distance(level: np.ndarray, camera: PlaneCamera, origin: np.ndarray,
                     spacing: np.ndarray) -> jax.Array:
    """(H, W) signed distance (mm, negative inside) on the grid to the 0 level of ``level`` (H, W), which is
    > 0 inside."""
    h, w = level.shape
    # The grid is regular in mm: node (row, col) is (xs[col], ys[row]).
    xs = origin[0] + np.arange(w, dtype=np.float64) * spacing[0]
    ys = origin[1] + np.arange(h, dtype=np.float64) * spacing[1]
    if camera.faces_camera:  # grid points are the pixel centres
        margin, outline = 0, level
    else:  # grid points anywhere on the image's footprint and a little beyond (a homography maps the
        # grid's rectangle to a quadrilateral: its corners reach farthest)
        corners_px = camera.grid_mm_to_px(xs[[0, -1]], ys[[0, -1]])
        reach = max(0.0, -corners_px.min(), float((corners_px - (w - 1.0, h - 1.0)).max()))
        margin = int(np.ceil(reach)) + 1
        outline = cv2.copyMakeBorder(level, margin, margin, margin, margin, cv2.BORDER_REPLICATE)
    segments_mm = camera.px_to_mm(_zero_crossings(outline) - margin)
    params = _nearest_segments(xs, ys, segments_mm, origin, spacing, _EXACT_BAND_PX * float(np.max(spacing)))
    homography = None if camera.faces_camera else _plane_to_px(camera)
    dtype = jnp.result_type(float)
    return _grid_distance(jnp.asarray(level), *params, jnp.asarray(xs, dtype), jnp.asarray(ys, dtype),
                          jnp.asarray(spacing, dtype), homography)


def _plane_to_px(camera: PlaneCamera) -> jax.Array:
    """(3, 3) the homography taking plane points (x, y, 1) in mm to homogeneous pixels (as
    :meth:`PlaneCamera.grid_mm_to_px`), in the default float type."""
    ex, ey, n = camera.axes
    origin = np.array([0.0, 0.0, camera.depth_mm]) + camera.offset_mm * n
    i = camera.intrinsics
    k = np.array([[i.fx, 0.0, i.ppx], [0.0, i.fy, i.ppy], [0.0, 0.0, 1.0]])
    return jnp.asarray(k @ np.column_stack([ex, ey, origin]), jnp.result_type(float))


def _zero_crossings(level: np.ndarray) -> np.ndarray:
    """Marching squares: the 0 level of ``level`` (H, W) as segments (S, 2, 2) of (u, v) px.

    Each cell between four pixel centres with both signs gets one segment (two at a saddle,
    separated as the cell's mean says) between the level's crossings of its edges, interpolated
    linearly between the edge's two pixel centres.
    """
    positive = level > 0
    # Only cells with a positive corner can be crossed: those of the box around the positive
    # values, one pixel wider (np.nonzero's row-major order of the cells is kept).
    rows, cols = np.flatnonzero(positive.any(axis=1)), np.flatnonzero(positive.any(axis=0))
    if len(rows):
        top, left = max(0, int(rows[0]) - 1), max(0, int(cols[0]) - 1)
        positive = positive[top:int(rows[-1]) + 2, left:int(cols[-1]) + 2]
        level = level[top:int(rows[-1]) + 2, left:int(cols[-1]) + 2]
    else:
        top = left = 0
    f00, f01, f10, f11 = level[:-1, :-1], level[:-1, 1:], level[1:, :-1], level[1:, 1:]
    s00, s01, s10, s11 = positive[:-1, :-1], positive[:-1, 1:], positive[1:, :-1], positive[1:, 1:]
    # Edges: top (00-01), right (01-11), bottom (10-11), left (00-10).
    crossed = np.stack([s00 != s01, s01 != s11, s10 != s11, s00 != s10], axis=-1)
    count = crossed.sum(axis=-1)
    cell_rows, cell_cols = np.nonzero(count >= 2)
    cut = crossed[cell_rows, cell_cols]
    corners = [f[cell_rows, cell_cols].astype(np.float64) for f in (f00, f01, f10, f11)]
    i, j = (cell_rows + top).astype(np.float64), (cell_cols + left).astype(np.float64)

    def at(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # where the line from a to b crosses 0
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(a != b, a / (a - b), 0.5)

    c00, c01, c10, c11 = corners
    points = np.stack([np.stack([j + at(c00, c01), i], -1), np.stack([j + 1.0, i + at(c01, c11)], -1),
                       np.stack([j + at(c10, c11), i + 1.0], -1), np.stack([j, i + at(c00, c10)], -1)], 1)
    single = count[cell_rows, cell_cols] == 2
    first = np.argmax(cut[single], axis=1)  # the two crossed edges, in order
    second = 3 - np.argmax(cut[single][:, ::-1], axis=1)
    pick = np.arange(int(single.sum()))
    pairs = [np.stack([points[single][pick, first], points[single][pick, second]], 1)]
    saddle = ~single
    if saddle.any():
        p = points[saddle]
        centre_inside = (c00 + c01 + c10 + c11)[saddle] > 0
        corner_cut = (s00[cell_rows, cell_cols][saddle] != centre_inside)[:, None]  # 00 and 11 cut off
        pairs.append(np.stack([np.where(corner_cut, p[:, 3], p[:, 0]), np.where(corner_cut, p[:, 0], p[:, 1])], 1))
        pairs.append(np.stack([np.where(corner_cut, p[:, 1], p[:, 2]), np.where(corner_cut, p[:, 2], p[:, 3])], 1))
    return np.concatenate(pairs)


def _nearest_segments(xs: np.ndarray, ys: np.ndarray, segments: np.ndarray, origin: np.ndarray,
                      spacing: np.ndarray, band_mm: float) -> tuple[jax.Array, jax.Array, jax.Array]:
    """What :func:`_grid_distance` needs of the segments (S, 2, 2) mm near the grid points
    (xs[col], ys[row]) (W,), (H,): the flat index (H, W) int32 of each grid point's nearest seed (a
    grid point at a corner of a cell the outline crosses; scipy's Euclidean feature transform), and
    (4, H W), for the grid points within ``band_mm`` of the seeds, their nearest segment (a, b - a)
    with a relative to the grid point (zero elsewhere), with (H W,) their exact distance to it
    (infinite elsewhere); JAX arrays of the default float type.
    """
    h, w = len(ys), len(xs)
    t = np.linspace(0.0, 1.0, _SAMPLES_PER_SEGMENT + 1)
    samples = (segments[:, :1] + t[None, :, None] * (segments[:, 1:] - segments[:, :1])).reshape(-1, 2)
    owner = np.repeat(np.arange(len(segments)), len(t))
    tree = cKDTree(samples)
    # Grid points at the corners of the grid cells the outline crosses, seeding the feature transform.
    cell = np.floor((samples - origin) / spacing).astype(np.int64)
    seed = np.zeros((h, w), bool)
    for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
        c, r = cell[:, 0] + dc, cell[:, 1] + dr
        ok = (c >= 0) & (c < w) & (r >= 0) & (r < h)
        seed[r[ok], c[ok]] = True
    to_seed, (seed_row, seed_col) = ndimage.distance_transform_edt(~seed, sampling=(spacing[1], spacing[0]),
                                                                     return_indices=True)
    near_row, near_col = np.nonzero(to_seed <= band_mm)
    near_nodes = np.stack([xs[near_col], ys[near_row]], axis=-1)
    k = min(_NEAREST_SAMPLES, len(samples))  # >= 2: every segment has several samples
    _, index = tree.query(near_nodes, k=k)
    candidates = owner[index]
    near_distance, best = _nearest_on(near_nodes, segments, candidates)
    nearest = segments[candidates[np.arange(len(best)), best]]
    near_flat = near_row * w + near_col
    dtype = jnp.result_type(float)
    band = np.zeros((4, h * w), dtype)
    band[:, near_flat] = np.concatenate([nearest[:, 0] - near_nodes, nearest[:, 1] - nearest[:, 0]], axis=1).T
    exact = np.full(h * w, np.inf, dtype)
    exact[near_flat] = near_distance
    seed_flat = (seed_row * w + seed_col).astype(np.int32)
    return jax.device_put(seed_flat), jax.device_put(band), jax.device_put(exact)  # (faster than jnp.asarray)


@jax.jit
def _grid_distance(level: jax.Array, seed_flat: jax.Array, band: jax.Array, exact: jax.Array, xs: jax.Array,
                   ys: jax.Array, spacing: jax.Array, homography: jax.Array | None) -> jax.Array:
    """(H, W) signed distance (mm, negative inside) on the grid (xs[col], ys[row]) (W,), (H,) mm: within
    the band, the exact distance (``exact``); beyond it, the distance to the segment of the grid
    point's nearest seed (its ``band`` column): a distance to a point of the outline, so never
    below the true one. Its arithmetic is relative to the seed (whole grid steps from it, then the
    segment's offset from it), so that float32 keeps its precision near the outline and a grid
    shifted by whole steps holds the same values. The sign is that of ``level``
    (H, W) at the grid point: the pixel itself when ``homography`` is None (a plane facing the camera,
    whose grid points are the pixel centres), otherwise bilinear at the pixel it maps the grid point to
    (the image's edge values continued beyond it).
    """
    h, w = level.shape
    px, py = xs[None, :], ys[:, None]
    ox, oy, abx, aby = (band[k][seed_flat] for k in range(4))
    steps_x = jnp.arange(w, dtype=jnp.int32)[None, :] - seed_flat % w
    steps_y = jnp.arange(h, dtype=jnp.int32)[:, None] - seed_flat // w
    apx = steps_x.astype(ox.dtype) * spacing[0] - ox  # from the segment's start a to the grid point
    apy = steps_y.astype(oy.dtype) * spacing[1] - oy
    abab = abx * abx + aby * aby
    along = jnp.where(abab > 0.0, (apx * abx + apy * aby) / jnp.where(abab > 0.0, abab, 1.0), 0.0)
    along = jnp.clip(along, 0.0, 1.0)  # the foot's position along its segment
    to_segment = jnp.hypot(apx - along * abx, apy - along * aby)
    exact = exact.reshape(h, w)
    distance = jnp.where(jnp.isfinite(exact), exact, to_segment)  # (the band's from float64 arithmetic)
    if homography is None:
        inside = level > 0.0
    else:
        q = homography[:, 0, None, None] * px + homography[:, 1, None, None] * py + homography[:, 2, None, None]
        u = jnp.clip(q[0] / q[2], 0.0, w - 1.0)
        v = jnp.clip(q[1] / q[2], 0.0, h - 1.0)
        u0 = jnp.minimum(jnp.floor(u), w - 2.0)
        v0 = jnp.minimum(jnp.floor(v), h - 2.0)
        fu, fv = u - u0, v - v0
        i, j = v0.astype(jnp.int32), u0.astype(jnp.int32)
        top = level[i, j] * (1.0 - fu) + level[i, j + 1] * fu
        bottom = level[i + 1, j] * (1.0 - fu) + level[i + 1, j + 1] * fu
        inside = top * (1.0 - fv) + bottom * fv > 0.0
    return jnp.where(inside, -distance, distance)


def _nearest_on(points: np.ndarray, segments: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (P,) from points (P, 2) to the nearest of their K candidate segments (P, K) (indices
    into segments (S, 2, 2)), and which of the K it is (P,)."""
    ax, ay = segments[:, 0, 0][candidates], segments[:, 0, 1][candidates]
    abx, aby = segments[:, 1, 0][candidates] - ax, segments[:, 1, 1][candidates] - ay
    apx, apy = points[:, :1] - ax, points[:, 1:] - ay
    abab = abx * abx + aby * aby
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.nan_to_num((apx * abx + apy * aby) / abab), 0.0, 1.0)  # the foot along the segment
    apx -= t * abx
    apy -= t * aby
    squared = apx * apx + apy * apy
    best = np.argmin(squared, axis=1)
    return np.sqrt(squared[np.arange(len(points)), best]), best


def object_polygon(mask: np.ndarray, camera: PlaneCamera, tolerance_px: float = 0.5) -> PolygonSDF:
    """The outline of the mask's largest object component as a polygon in mm.

    The contour is traced (``cv2.findContours``) on the mask upsampled 4x, so it runs within 1/8 px
    of the pixel boundary, then simplified with ``cv2.approxPolyDP`` to ``tolerance_px``. Where the
    object is cut by the image border the polygon closes along the border, a boundary the real
    object does not have: prefer :func:`object_sdf` for such objects.

    Args:
        mask: (H, W) bool, the object's pixels.
        camera: the gripper plane's camera.
        tolerance_px: largest distance (px) of the traced contour from the simplified polygon, > 0.

    Returns:
        ``PolygonSDF`` with vertices (V, 2) in mm, V >= 3.

    Example:
        >>> import numpy as np
        >>> from synthetic.render import d405_intrinsics
        >>> mask = np.zeros((480, 640), bool); mask[200:260, 300:360] = True
        >>> object_polygon(mask, PlaneCamera(d405_intrinsics(), 120.0)).vertices.shape
        (4, 2)

    Raises:
        ObjectMaskError: an empty mask (no object: use :func:`object_sdf`, which handles it), or a
            bad tolerance.
    """
    inside = _as_mask(mask)
    if not (np.isfinite(tolerance_px) and tolerance_px > 0):
        raise ObjectMaskError(f"object_polygon: tolerance_px must be a finite number of pixels > 0, got "
                              f"{tolerance_px!r}")
    if not inside.any():
        raise ObjectMaskError("object_polygon: the object mask is empty (no object in the frame); "
                              "object_sdf handles that case")
    rows, cols = np.nonzero(inside)
    top, left = rows.min(), cols.min()
    crop = inside[top:rows.max() + 1, left:cols.max() + 1].view(np.uint8)
    k = _POLYGON_UPSAMPLE
    fine = cv2.resize(crop, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(fine, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = cv2.approxPolyDP(max(contours, key=cv2.contourArea), tolerance_px * k, closed=True)
    # Upsampled pixel j covers original coordinates [j/k - 1/2, (j+1)/k - 1/2]; its centre:
    vertices_px = (outline.reshape(-1, 2) + 0.5) / k - 0.5 + (left, top)
    if len(vertices_px) < 3:  # a sliver simplified to a segment: keep the traced contour
        vertices_px = (max(contours, key=cv2.contourArea).reshape(-1, 2) + 0.5) / k - 0.5 + (left, top)
    return PolygonSDF(jnp.asarray(camera.px_to_mm(vertices_px), jnp.result_type(float)))


def _as_mask(mask: np.ndarray) -> np.ndarray:
    inside = np.asarray(mask, dtype=bool)
    if inside.ndim != 2 or min(inside.shape) < 2:
        raise ObjectMaskError(f"the object mask must be a 2-D (H, W) array of at least 2x2, got shape "
                              f"{inside.shape}")
    return np.ascontiguousarray(inside)
