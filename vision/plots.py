"""Plots people read, drawn with matplotlib: the score heat map over the frame, in millimetres.

matplotlib is optional (``pip install softgrip-jax[plots]``) and imported only when a plot is made;
without it :func:`require_matplotlib` raises a :class:`~softgrip_jax.SoftgripError` that says so.
Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas, never through pyplot, so
no global backend or figure state changes in the caller's process. Per-frame overlays for video
(joints and contacts drawn on each frame's pixels) stay OpenCV drawings
(:mod:`vision.overlay`).

The heat map (:func:`heatmap_figure`) shows the frame in the gripper plane's millimetres (x right,
y down, as the image), each gripper-centre position of a pose grid coloured by its best score over
the angles (grey: no valid candidate there), with a colour bar, the best candidate's estimated
fingers and contacts, its centre and base line, and a legend; the axes span the whole frame and the
whole grid, even where the grid reaches beyond the image.
"""

from __future__ import annotations

import io
import math
import os
from typing import Any

import numpy as np

from softgrip_jax import SoftgripError

INSTALL_HINT = "pip install softgrip-jax[plots]"


def require_matplotlib():
    """The ``matplotlib`` module, or a SoftgripError naming the extra to install."""
    try:
        import matplotlib
    except ImportError:
        raise SoftgripError(f"plots need matplotlib, which is not installed: {INSTALL_HINT}") from None
    return matplotlib


def figure_format(path: str | os.PathLike[str], what: str = "output") -> str:
    """The image format of ``path`` from its extension (``.png``, ``.jpg``, ``.pdf``, ``.svg``, ...:
    the formats matplotlib's Agg canvas writes); a SoftgripError naming them otherwise."""
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    supported = FigureCanvasAgg(Figure()).get_supported_filetypes()
    suffix = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    if suffix not in supported:
        raise SoftgripError(f"{what} {path}: cannot tell the image format from the extension "
                            f"{('.' + suffix) if suffix else '(none)'}; use one of "
                            f"{', '.join('.' + s for s in sorted(supported))}")
    return suffix


def save_figure(figure, path: str | os.PathLike[str], *, inputs=(), force: bool = False, what: str = "output",
                dpi: int = 120) -> None:
    """Write ``figure`` to ``path`` in the format its extension names, atomically (the output
    policy of :mod:`softgrip_base.atomic_write`)."""
    from softgrip_base.atomic_write import write_atomic

    fmt = figure_format(path, what)
    buffer = io.BytesIO()
    figure.savefig(buffer, format=fmt, dpi=dpi, bbox_inches="tight", facecolor="white")
    data = buffer.getvalue()
    if fmt == "png":  # matplotlib writes RGBA; an opaque plot is an RGB PNG, as every other picture here
        import cv2

        data = cv2.imencode(".png", cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR))[1].tobytes()
    try:
        write_atomic(path, data, inputs=inputs, force=force, what=what)
    except OSError as err:
        raise SoftgripError(f"{what} {path}: cannot write it ({err.strerror}); it is left as it was") from None


def _best_over_angles(scores: np.ndarray, grid) -> np.ndarray:
    """(NY, NX) best valid score at each gripper-centre position of ``grid`` (NaN: none valid)."""
    xs, ys, angles = grid
    per_angle = scores.reshape(len(xs), len(ys), len(angles))
    best = np.full((len(xs), len(ys)), np.nan)
    has_valid = np.isfinite(per_angle).any(axis=2)
    best[has_valid] = np.nanmax(per_angle[has_valid], axis=1)
    return best.T


def _cell_edges(values: np.ndarray) -> tuple[float, float]:
    step = (values[-1] - values[0]) / (len(values) - 1) if len(values) > 1 else 2.0
    return float(values[0] - step / 2), float(values[-1] + step / 2)


def heatmap_figure(scene, poses: np.ndarray, result, grid=None, best: int | None = None, *,
                   title: str | None = None):
    """A matplotlib ``Figure`` of the scores of ``poses`` on ``scene`` (see the module docstring).

    Args:
        scene: a :class:`vision.scene.Scene`.
        poses: (B, 3) poses (x mm, y mm, angle rad).
        result: their numpy :class:`softgrip_jax.Score` (:meth:`vision.scene.Scene.score`).
        grid: ``(xs, ys, angles)`` when the poses are that grid (x slowest, angle fastest): drawn
            as cells; None: each pose's centre is drawn as a dot.
        best: index of the pose whose estimate is drawn (default: the best valid score).
        title: the figure's title (default: the frame's name and what is shown).
    """
    require_matplotlib()
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from vision.documents import SIDES, finger_contacts_mm

    poses = np.asarray(poses, np.float64)
    scores = np.where(np.asarray(result.valid), np.asarray(result.score, np.float64), np.nan)
    finite = scores[np.isfinite(scores)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    if best is None and finite.size:
        best = int(np.nanargmax(scores))
    cmap = colormaps["viridis"].with_extremes(bad=(0.5, 0.5, 0.5, 0.55))

    figure = Figure(figsize=(8.0, 6.6), layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    h, w = scene.frame.color.shape[:2]
    (x0, y0), (x1, y1) = scene.camera.px_to_mm([[-0.5, -0.5], [w - 0.5, h - 0.5]])
    ax.imshow(scene.frame.color, extent=(x0, x1, y1, y0), interpolation="bilinear")
    spans_x, spans_y = [x0, x1], [y0, y1]
    if grid is not None:
        cells = _best_over_angles(scores, grid)
        gx0, gx1 = _cell_edges(np.asarray(grid[0]))
        gy0, gy1 = _cell_edges(np.asarray(grid[1]))
        image = ax.imshow(np.ma.masked_invalid(cells), extent=(gx0, gx1, gy1, gy0), cmap=cmap, vmin=lo, vmax=hi,
                          alpha=0.75, interpolation="nearest")
        ax.add_patch(_rectangle(gx0, gy0, gx1, gy1))
        spans_x += [gx0, gx1]
        spans_y += [gy0, gy1]
        label = f"best score over {len(grid[2])} angle{'s' if len(grid[2]) != 1 else ''}"
    else:
        order = np.argsort(np.nan_to_num(scores, nan=-np.inf), kind="stable")  # best drawn last, on top
        image = ax.scatter(poses[order, 0], poses[order, 1], c=np.ma.masked_invalid(scores[order]), cmap=cmap,
                           vmin=lo, vmax=hi, s=28, edgecolors="white", linewidths=0.4, plotnonfinite=True)
        spans_x += [float(poses[:, 0].min()), float(poses[:, 0].max())]
        spans_y += [float(poses[:, 1].min()), float(poses[:, 1].max())]
        label = "score"
    # The bar shows the colours at full strength (the cells are drawn see-through over the frame).
    bar = figure.colorbar(ScalarMappable(norm=Normalize(lo, hi), cmap=cmap), ax=ax, shrink=0.85)
    bar.set_label(label if finite.size else f"{label} (no valid candidate)")

    handles = [Patch(facecolor=(0.5, 0.5, 0.5, 0.55), label="no valid candidate")]
    if best is not None and bool(np.asarray(result.valid)[best]):
        chosen = _row(result, best)
        for k, side in enumerate(SIDES):
            joints = np.asarray(getattr(chosen.grasp, side).joints, np.float64)
            ax.plot(joints[:, 0], joints[:, 1], "-", color="white", lw=4.0, solid_capstyle="round")
            ax.plot(joints[:, 0], joints[:, 1], "o-", color="tab:blue", lw=2.0, ms=2.5)
            contacts = finger_contacts_mm(getattr(chosen.grasp, side))
            if len(contacts):
                ax.plot(contacts[:, 0], contacts[:, 1], "o", color="tab:red", ms=7, mec="white", mew=1.2)
        x, y, angle = poses[best]
        half = 0.5 * float(scene.gripper.base_separation) * np.array([math.cos(angle), -math.sin(angle)])
        ends = np.array([[x, y] - half, [x, y] + half])
        ax.plot(ends[:, 0], ends[:, 1], "-", color="black", lw=1.5)
        ax.plot([x], [y], "+", color="black", ms=14, mew=2.5)
        spans_x += list(ends[:, 0])
        spans_y += list(ends[:, 1])
        handles = [Line2D([], [], color="tab:blue", marker="o", ms=3, label="best pose: estimated fingers"),
                   Line2D([], [], color="tab:red", marker="o", ls="", label="contacts on the object"),
                   Line2D([], [], color="black", marker="+", ms=10, mew=2, lw=1.5,
                          label=f"its centre and finger bases (score {float(chosen.score):.2f})"),
                   *handles]
    ax.legend(handles=handles, loc="lower left", fontsize="small", framealpha=0.85)
    margin = 3.0
    ax.set_xlim(min(spans_x) - margin, max(spans_x) + margin)
    ax.set_ylim(max(spans_y) + margin, min(spans_y) - margin)  # y down, as in the image
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, gripper plane)")
    ax.set_ylabel("y (mm, down)")
    if best is not None and bool(np.asarray(result.valid)[best]):
        x, y, angle = poses[best]
        subtitle = f"best: x {x:.1f} mm, y {y:.1f} mm, angle {angle:.2f} rad"
    else:
        subtitle = "no valid candidate"
    ax.set_title(title or f"{scene.name}: score of each gripper-centre position\n{subtitle}", fontsize="medium")
    return figure


def _rectangle(x0: float, y0: float, x1: float, y1: float):
    from matplotlib.patches import Rectangle

    return Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="white", lw=1.0, ls="--")


def _row(tree: Any, index: int):
    import jax

    return jax.tree_util.tree_map(lambda x: x[index], tree)
