"""Object mask -> signed distance in millimetres, as the core's ``SDFGrid`` or ``PolygonSDF``.

The grid has one value per pixel. OpenCV's exact Euclidean distance transform
(``cv2.distanceTransform(..., cv2.DIST_L2, cv2.DIST_MASK_PRECISE)``) gives, for each pixel, the
distance to the nearest pixel centre of the other kind (object / not object). The object's boundary
runs between the two kinds of pixel centres, so half a pixel is taken off both sides:

    sdf = d_outside - 1/2 outside the object,    sdf = 1/2 - d_inside inside it   (px),

and bilinear interpolation (the core's lookup) puts the zero level halfway between an object pixel
and its neighbour outside: on the boundary to sub-pixel accuracy. Pixel distances become
millimetres with the plane camera's ``mm_per_px`` (exact for square pixels, fx = fy; otherwise off
by at most ``|fx - fy| / (2 min(fx, fy))`` relative, 0.1 % for a typical D405, and exactly 0 on the
zero level). The grid's origin is the millimetre position of pixel (0, 0) and its spacing the pixel
size (Z / fx, Z / fy), so grid element (row v, column u) is pixel (u, v).

**Objects cut by the image border.** The part outside the image is unknown. The image border is
not treated as the object's boundary: inside the image, distances are to the visible boundary
only (an object pixel at the border has a negative value), and outside the image the core reads
the grid as far (``SDFGrid.far``), i.e. never in contact. Contacts predicted near the border are
therefore only as good as the visible part of the object.

Example:
    >>> import numpy as np
    >>> from vision.synthetic.render import d405_intrinsics
    >>> from vision.geometry import PlaneCamera
    >>> mask = np.zeros((480, 640), bool); mask[200:260, 300:360] = True
    >>> grid = object_sdf(mask, PlaneCamera(d405_intrinsics(), 120.0))
    >>> grid.values.shape
    (480, 640)
"""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np

from softgrip_jax import FAR_MM, PolygonSDF, SDFGrid, SoftgripError
from vision.geometry import PlaneCamera

_POLYGON_UPSAMPLE = 4


class ObjectMaskError(SoftgripError):
    """An object mask that cannot be turned into a signed-distance function."""


def object_sdf(mask: np.ndarray, camera: PlaneCamera) -> SDFGrid:
    """Signed distance (mm, negative inside) to the object in ``mask``, one grid value per pixel.

    Args:
        mask: (H, W) bool, the object's pixels (several components are one object).
        camera: the gripper plane's camera (mm per pixel and pixel (0, 0)'s position).

    Returns:
        ``SDFGrid`` with values (H, W) in mm, origin (2,) = pixel (0, 0) in mm, spacing (2,) =
        (Z / fx, Z / fy) mm. An empty mask (no object) gives a grid that reads ``FAR_MM``
        everywhere: nothing can be touched (contact case (a)).

    Example (a 60 x 60 px square; at 120 mm one pixel is 120 / 385 mm):
        >>> import numpy as np
        >>> from vision.synthetic.render import d405_intrinsics
        >>> camera = PlaneCamera(d405_intrinsics(), 120.0)
        >>> mask = np.zeros((480, 640), bool); mask[200:260, 300:360] = True
        >>> grid = object_sdf(mask, camera)
        >>> point = camera.px_to_mm(np.array([310.0, 229.5]))  # mm; the left edge is at u = 299.5
        >>> round(float(grid.distance(jnp.asarray(point))) / camera.mm_per_px, 2)  # 10.5 px inside
        -10.5

    Raises:
        ObjectMaskError: the mask is not 2-D or is smaller than 2x2, or covers the whole frame
            (no boundary: check the object's colour thresholds and the background cut-off).
    """
    inside = _as_mask(mask)
    if not inside.any():
        values = np.full(inside.shape, FAR_MM, dtype=np.float32)
    elif inside.all():
        raise ObjectMaskError("the object mask covers the whole frame, so it has no boundary: check "
                              "object_min_saturation and background_depth_mm of the segmentation")
    else:
        u8 = inside.view(np.uint8)
        d_inside = cv2.distanceTransform(u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        d_outside = cv2.distanceTransform(1 - u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        values = np.where(inside, 0.5 - d_inside, d_outside - 0.5) * np.float32(camera.mm_per_px)
    dtype = jnp.result_type(float)
    return SDFGrid(values=jnp.asarray(values, dtype), origin=jnp.asarray(camera.origin_mm, dtype),
                   spacing=jnp.asarray(camera.spacing_mm, dtype))


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
        >>> from vision.synthetic.render import d405_intrinsics
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
