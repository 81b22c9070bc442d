"""Plots people read, drawn with matplotlib: the grasp-quality heat map and the top grasps with their
friction cones over the frame, in millimetres.

matplotlib is optional (``pip install softgrip-jax[plots]``) and imported only when a plot is made;
without it :func:`require_matplotlib` raises a :class:`~softgrip_jax.SoftgripError` that says so.
Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas, never through pyplot, so
no global backend or figure state changes in the caller's process. Per-frame overlays for video
(joints and contacts drawn on each frame's pixels) stay OpenCV drawings
(:mod:`softgrip_vision.overlay`).

The heat map (:func:`heatmap_figure`) shows the frame in the gripper plane's millimetres (x right,
y down, as the image), each gripper-centre position of a pose grid coloured by its best grasp
quality over the angles (the Ferrari-Canny L1 epsilon; light grey: valid candidates there but none in
force closure, dark grey: no valid candidate), with a colour bar, the best candidate's estimated
fingers and contacts, its centre and base line, and a legend; the axes span the whole frame and the
whole grid, even where the grid reaches beyond the image.

The grasps picture (:func:`grasps_figure`) shows the frame in millimetres with the best few valid
candidates: each one's estimated fingers and, at each contact the quality is computed from, the
friction cone (its two edges at ``atan(mu)`` about the inward normal) and the contact force on the
object when the estimate gives forces (the mechanics one).
"""

from __future__ import annotations

import io
import math
import os
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from jaxtyping import ArrayLike, Float

from softgrip_base.input_guard import one_line
from softgrip_jax import SoftgripError
from softgrip_jax._quality import DEFAULT_MU

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from softgrip_jax import Score
    from softgrip_vision.scene import Scene

#: A grid of candidate poses as its three axes: gripper-centre x (mm), y (mm) and angle (rad), each (n,).
PoseGrid = tuple[Any, Any, Any]

INSTALL_HINT = "pip install softgrip-jax[plots]"
#: RGBA of a position (or pose) with valid candidates but none in force closure, and of one with none valid.
NO_CLOSURE_RGBA = (0.95, 0.95, 0.95, 0.85)
NO_VALID_RGBA = (0.2, 0.2, 0.2, 0.6)
#: Valid candidates :func:`grasps_figure` draws, best first, and its size (inches).
TOP_GRASPS = 5
GRASPS_FIGSIZE = (10.0, 7.5)


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


def save_figure(figure: Figure, path: str | os.PathLike[str], *, inputs=(), force: bool = False, what: str = "output",
                dpi: int = 120, tight: bool = True) -> None:
    """Write ``figure`` to ``path`` in the format its extension names, atomically (the output
    policy of :mod:`softgrip_base.atomic_write`): cropped to what is drawn (``tight``), or the
    figure's own size (its inches times ``dpi``)."""
    from softgrip_base.atomic_write import write_atomic

    fmt = figure_format(path, what)
    buffer = io.BytesIO()
    figure.savefig(buffer, format=fmt, dpi=dpi, bbox_inches="tight" if tight else None, facecolor="white")
    data = buffer.getvalue()
    if fmt == "png":  # matplotlib writes RGBA; an opaque plot is an RGB PNG, as every other picture here
        import cv2

        opaque: np.ndarray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)  # type: ignore[assignment]
        data = cv2.imencode(".png", opaque)[1].tobytes()
    try:
        write_atomic(path, data, inputs=inputs, force=force, what=what)
    except OSError as err:
        raise SoftgripError(f"{what} {path}: cannot write it ({err.strerror}); it is left as it was") from None


def _best_over_angles(values: np.ndarray, grid) -> np.ndarray:
    """(NY, NX) largest finite value over the angles at each gripper-centre position of ``grid``
    (NaN: none finite); ``values`` (B,) in the grid's order (x slowest, angle fastest)."""
    xs, ys, angles = grid
    per_angle = values.reshape(len(xs), len(ys), len(angles))
    best = np.full((len(xs), len(ys)), np.nan)
    has_value = np.isfinite(per_angle).any(axis=2)
    best[has_value] = np.nanmax(per_angle[has_value], axis=1)
    return best.T


def closure_quality(result: Score, robust: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Each candidate's grasp quality where it is valid and in force closure (NaN elsewhere), and
    whether it is valid: two (B,) arrays of a numpy :class:`softgrip_jax.Score`. ``robust``: the
    probability of force closure instead (robust scoring's ``p_closure``, NaN where 0)."""
    valid = np.asarray(result.valid, bool)
    if robust:
        p = np.asarray(result.p_closure, np.float64)
        return np.where(valid & (p > 0), p, np.nan), valid
    closure = valid & np.asarray(result.force_closure, bool)
    return np.where(closure, np.asarray(result.quality, np.float64), np.nan), valid


def quality_cells(result: Score, grid: PoseGrid, robust: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(NY, NX) best quality over the angles at each gripper-centre position of ``grid`` (NaN: no
    candidate there in force closure), and (NY, NX) whether any candidate there is valid.
    ``robust``: the best probability of force closure instead."""
    quality, valid = closure_quality(result, robust)
    return _best_over_angles(quality, grid), np.isfinite(_best_over_angles(np.where(valid, 0.0, np.nan), grid))


def _plain(name: str) -> str:
    """A frame's name as matplotlib draws it literally: control characters and bytes that were not
    UTF-8 escaped (:func:`softgrip_base.input_guard.one_line`), and '$' not read as mathtext."""
    return one_line(name).replace("$", r"\$")


def quality_label(mu: float) -> str:
    """The quality's label in the plots: what it is and the friction it assumes."""
    return f"quality (Ferrari-Canny L1, mu = {mu:g})"


def _quality_rgba(quality: np.ndarray, valid: np.ndarray, cmap, norm) -> np.ndarray:
    """RGBA (..., 4) of qualities (NaN: no closure): the colour map where in closure,
    :data:`NO_CLOSURE_RGBA` where valid without closure, :data:`NO_VALID_RGBA` where not valid."""
    rgba = np.asarray(cmap(norm(np.nan_to_num(quality, nan=0.0))), np.float64)
    rgba[~np.isfinite(quality)] = NO_CLOSURE_RGBA
    rgba[~valid] = NO_VALID_RGBA
    return rgba


def _cell_edges(values: np.ndarray) -> tuple[float, float]:
    step = (values[-1] - values[0]) / (len(values) - 1) if len(values) > 1 else 2.0
    return float(values[0] - step / 2), float(values[-1] + step / 2)


def _frame_axes(scene: Scene, figsize: tuple[float, float],
                layout: Literal["constrained", "compressed", "tight"] | None = "constrained"):
    """A ``Figure`` (Agg canvas, no pyplot; matplotlib's ``layout``) with one axes showing the frame
    in the gripper plane's mm; and the axes, with the x and y spans (mm) drawn so far."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=figsize, layout=layout)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    h, w = scene.frame.color.shape[:2]
    (x0, y0), (x1, y1) = scene.camera.px_to_mm([[-0.5, -0.5], [w - 0.5, h - 0.5]])
    ax.imshow(scene.frame.color, extent=(x0, x1, y1, y0), interpolation="bilinear")
    return figure, ax, [x0, x1], [y0, y1]


def _finish_axes(ax, spans_x: list[float], spans_y: list[float], margin: float = 3.0) -> None:
    """Limits that hold everything drawn (mm, y down as in the image), equal aspect, axis labels."""
    ax.set_xlim(min(spans_x) - margin, max(spans_x) + margin)
    ax.set_ylim(max(spans_y) + margin, min(spans_y) - margin)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, gripper plane)")
    ax.set_ylabel("y (mm, down)")


def _draw_fingers(ax, grasp, colour) -> np.ndarray:
    """Both fingers' estimated joints (mm) of one candidate, over a white outline; returns them, (2 (N+1), 2)."""
    from softgrip_vision.documents import SIDES

    drawn = []
    for side in SIDES:
        joints = np.asarray(getattr(grasp, side).joints, np.float64)
        ax.plot(joints[:, 0], joints[:, 1], "-", color="white", lw=4.0, solid_capstyle="round")
        ax.plot(joints[:, 0], joints[:, 1], "o-", color=colour, lw=2.0, ms=2.5)
        drawn.append(joints)
    return np.concatenate(drawn)


def heatmap_figure(scene: Scene, poses: Float[np.ndarray, "b 3"], result: Score, grid: PoseGrid | None = None,
                   best: int | None = None, *, title: str | None = None, mu: float = DEFAULT_MU,
                   robust: bool = False) -> Figure:
    """A matplotlib ``Figure`` of the grasp quality of ``poses`` on ``scene`` (see the module docstring).

    Args:
        scene: a :class:`softgrip_vision.scene.Scene`.
        poses: (B, 3) poses (x mm, y mm, angle rad).
        result: their numpy :class:`softgrip_jax.Score` (:meth:`softgrip_vision.scene.Scene.score`).
        grid: ``(xs, ys, angles)`` when the poses are that grid (x slowest, angle fastest): drawn
            as cells, each the best quality over the angles; None: each pose's centre is drawn as a dot.
        best: index of the pose whose estimate is drawn (default: the best valid score).
        title: the figure's title (default: the frame's name and what is shown).
        mu: the friction coefficient the scores were computed with (for the colour bar's label).
        robust: show the probability of force closure (robust scoring's ``p_closure``) instead.
    """
    require_matplotlib()
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from softgrip_vision.documents import SIDES, quality_contacts

    poses = np.asarray(poses, np.float64)
    quality, valid = closure_quality(result, robust)
    scores = np.where(valid, np.asarray(result.score, np.float64), np.nan)
    finite = quality[np.isfinite(quality)]
    norm = Normalize(0.0, 1.0 if robust else float(finite.max()) if finite.size and finite.max() > 0 else 1.0)
    shown = "P(force closure)" if robust else quality_label(mu)
    if best is None and np.isfinite(scores).any():
        best = int(np.nanargmax(scores))
    cmap = colormaps["viridis"]

    figure, ax, spans_x, spans_y = _frame_axes(scene, (8.0, 6.6))
    if grid is not None:
        cells, any_valid = quality_cells(result, grid, robust)
        gx0, gx1 = _cell_edges(np.asarray(grid[0]))
        gy0, gy1 = _cell_edges(np.asarray(grid[1]))
        ax.imshow(_quality_rgba(cells, any_valid, cmap, norm), extent=(gx0, gx1, gy1, gy0), alpha=0.75,
                  interpolation="nearest")
        ax.add_patch(_rectangle(gx0, gy0, gx1, gy1))
        spans_x += [gx0, gx1]
        spans_y += [gy0, gy1]
        label = f"best {shown} over {len(grid[2])} angle{'s' if len(grid[2]) != 1 else ''}"
    else:
        order = np.argsort(np.nan_to_num(scores, nan=-np.inf), kind="stable")  # best drawn last, on top
        ax.scatter(poses[order, 0], poses[order, 1], c=_quality_rgba(quality[order], valid[order], cmap, norm), s=28,
                   edgecolors="white", linewidths=0.4)
        spans_x += [float(poses[:, 0].min()), float(poses[:, 0].max())]
        spans_y += [float(poses[:, 1].min()), float(poses[:, 1].max())]
        label = shown
    # The bar shows the colours at full strength (the cells are drawn see-through over the frame).
    bar = figure.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.85)
    bar.set_label(label if finite.size else f"{label} (no force closure)")

    handles: list[Any] = [Patch(facecolor=NO_CLOSURE_RGBA, edgecolor="grey", label="valid, no force closure"),
                          Patch(facecolor=NO_VALID_RGBA, label="no valid candidate")]
    if best is not None and bool(valid[best]):
        chosen = _row(result, best)
        _draw_fingers(ax, chosen.grasp, "tab:blue")
        for k in range(len(SIDES)):
            contacts = quality_contacts(chosen.contacts, k)["points"]
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
                   Line2D([], [], color="tab:red", marker="o", ls="", label="its contacts on the object"),
                   Line2D([], [], color="black", marker="+", ms=10, mew=2, lw=1.5,
                          label=f"its centre and finger bases (score {float(chosen.score):.2f})"),
                   *handles]
    ax.legend(handles=handles, loc="lower left", fontsize="small", framealpha=0.85)
    _finish_axes(ax, spans_x, spans_y)
    if best is not None and bool(valid[best]):
        x, y, angle = poses[best]
        subtitle = f"best: x {x:.1f} mm, y {y:.1f} mm, angle {angle:.2f} rad"
    else:
        subtitle = "no valid candidate"
    ax.set_title(title or f"{_plain(scene.name)}: grasp quality at each gripper-centre position\n{subtitle}",
                 fontsize="medium")
    return figure


def _unit(angle: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def _draw_contact(ax, point: np.ndarray, normal: np.ndarray, force, mu: float, colour, cone_mm: float,
                  force_mm: float | None) -> None:
    """One contact: its friction cone (the edges at ``atan(mu)`` about the inward normal ``-normal``,
    ``cone_mm`` long, filled see-through) and, when ``force_mm`` (mm per unit force) is given, the
    force on the object as an arrow from the contact."""
    inward = math.atan2(-normal[1], -normal[0])
    half = math.atan(mu)
    edges = point + cone_mm * _unit(np.array([inward - half, inward + half]))
    ax.fill([point[0], edges[0, 0], edges[1, 0]], [point[1], edges[0, 1], edges[1, 1]], color=colour, alpha=0.25,
            lw=0)
    for end in edges:
        ax.plot([point[0], end[0]], [point[1], end[1]], "-", color=colour, lw=1.2)
    ax.plot([point[0]], [point[1]], "o", color=colour, ms=5, mec="white", mew=1.0)
    if force_mm is not None and np.isfinite(force).all() and np.hypot(*force) > 0:
        tip = force * force_mm
        ax.annotate("", xy=tuple(point + tip), xytext=tuple(point),
                    arrowprops={"arrowstyle": "-|>", "color": "black", "lw": 1.4, "shrinkA": 0, "shrinkB": 0})


def grasps_figure(scene: Scene, poses: Float[np.ndarray, "b 3"], result: Score, order: ArrayLike | None = None, *,
                  top: int = TOP_GRASPS, mu: float = DEFAULT_MU, title: str | None = None,
                  cone_mm: float = 8.0) -> Figure:
    """A matplotlib ``Figure`` of the best ``top`` valid candidates on ``scene`` (see the module
    docstring): each one's estimated fingers in its own colour, its rank at its centre, and at each
    of its contacts the friction cone (``cone_mm`` mm long, half-angle ``atan(mu)``) and the contact
    force (mechanics estimate; the largest force drawn ``cone_mm`` long). The figure is
    :data:`GRASPS_FIGSIZE` inches, legend included (written at that size with ``save_figure(...,
    tight=False)``).

    Args:
        scene: a :class:`softgrip_vision.scene.Scene`.
        poses: (B, 3) poses (x mm, y mm, angle rad).
        result: their numpy :class:`softgrip_jax.Score` (:meth:`softgrip_vision.scene.Scene.score`).
        order: candidate indices, best first (default: :func:`softgrip_vision.scene.rank`); the first
            ``top`` valid ones are drawn.
        mu: the friction coefficient the scores were computed with.
        title: the figure's title (default: the frame's name and each grasp's rank, quality and closure).
    """
    require_matplotlib()
    from matplotlib import colormaps
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from softgrip_vision.documents import SIDES, quality_contacts
    from softgrip_vision.scene import rank

    poses = np.asarray(poses, np.float64)
    order = rank(result) if order is None else np.asarray(order)
    valid = np.asarray(result.valid, bool)
    drawn = [(k, int(i)) for k, i in enumerate(order, start=1) if valid[i]][:top]
    rows = {i: _row(result, i) for _, i in drawn}
    contacts = {i: [quality_contacts(rows[i].contacts, s) for s in range(len(SIDES))] for _, i in drawn}
    forces = [np.hypot(*c["forces"].T) for i in contacts for c in contacts[i] if c["forces"] is not None
              and len(c["forces"])]
    largest = max((float(np.nanmax(f)) for f in forces if np.isfinite(f).any()), default=0.0)
    force_mm = cone_mm / largest if largest > 0 else None

    # Fixed margins (the constrained layout lets a square axes push its y label out of the figure).
    figure, ax, spans_x, spans_y = _frame_axes(scene, GRASPS_FIGSIZE, layout=None)
    figure.subplots_adjust(left=0.08, right=0.68, bottom=0.08, top=0.86)
    if drawn:  # zoomed on the grasps: the fingers, contacts and centres drawn
        spans_x, spans_y = [], []
    colours = colormaps["tab10"].colors  # type: ignore[attr-defined]  # tab10 is a ListedColormap
    handles: list[Any] = []
    lines: list[str] = []
    for n, (k, i) in enumerate(drawn):
        colour, chosen = colours[n % len(colours)], rows[i]
        joints = _draw_fingers(ax, chosen.grasp, colour)
        joints = joints[np.isfinite(joints).all(axis=1)]
        spans_x += list(joints[:, 0])
        spans_y += list(joints[:, 1])
        for finger in contacts[i]:
            forces_i = finger["forces"] if finger["forces"] is not None else [None] * len(finger["points"])
            for point, normal, force in zip(finger["points"], finger["normals"], forces_i):
                _draw_contact(ax, point, normal, force, mu, colour, cone_mm, None if force is None else force_mm)
                spans_x.append(float(point[0]))
                spans_y.append(float(point[1]))
        x, y, _ = poses[i]
        ax.text(x, y, f"#{k}", color=colour, fontsize="small", fontweight="bold", ha="center", va="center",
                bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": colour, "alpha": 0.85})
        spans_x.append(float(x))
        spans_y.append(float(y))
        closure = "closure" if bool(chosen.force_closure) else "no closure"
        lines.append(f"#{k} {float(chosen.quality):.3f} {closure}")
        handles.append(Line2D([], [], color=colour, marker="o", ms=3, label=f"#{k}: score {float(chosen.score):.3f}"))
    handles.append(Patch(facecolor=(0.5, 0.5, 0.5, 0.25), edgecolor="grey",
                         label=f"friction cone: +-atan(mu) = {math.degrees(math.atan(mu)):.1f} deg"))
    if force_mm is not None:
        handles.append(Line2D([], [], color="black", marker=">", ms=5, lw=1.4,
                              label=f"force on object: {cone_mm:g} mm = {largest:.3g} EI/L^2"))
    figure.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.69, 0.86), fontsize="small", framealpha=0.85)
    if drawn:  # a square view about the grasps: the axes fill the figure's square space
        half = 0.5 * max(max(spans_x) - min(spans_x), max(spans_y) - min(spans_y))
        for spans in (spans_x, spans_y):
            middle = 0.5 * (max(spans) + min(spans))
            spans += [middle - half, middle + half]
    _finish_axes(ax, spans_x, spans_y, margin=cone_mm + 3.0)
    head = (f"{_plain(scene.name)}: the top {len(drawn)} valid grasp{'s' if len(drawn) != 1 else ''}, mu = {mu:g}"
            if drawn else f"{_plain(scene.name)}: no valid grasp")
    body = "\n".join(("quality: " if j == 0 else "") + ", ".join(lines[j:j + 3]) for j in range(0, len(lines), 3))
    ax.set_title(title or (head + ("\n" + body if body else "")), fontsize="medium")
    return figure


def _rectangle(x0: float, y0: float, x1: float, y1: float):
    from matplotlib.patches import Rectangle

    return Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="white", lw=1.0, ls="--")


def _row(tree: Any, index: int):
    import jax

    return jax.tree_util.tree_map(lambda x: x[index], tree)
