"""Multi-frame least-squares calibration through the differentiable core.

Each observation is an open/closed frame pair: the object's signed distance and both finger bases
seen in the open frame, and both fingers' observed joints in the closed frame (the closed centreline
divided into N equal arc lengths, as in the paper's evaluation). For parameters ``p`` the residuals
are, for every frame, finger and joint,

    r = estimate_in_frame(finger(p), sdf, FingerFrame(base + base_offset(p))).joints - observed   (mm)

and the fit minimises ``sum rho(|r|)`` over the joints of all usable frames with optimistix's
Levenberg-Marquardt solver in float64, differentiating through the core's contact prediction and
deformation (forward mode). ``rho`` is a robust loss on each joint's distance (Huber or Cauchy,
scale about 1 mm), written as the residual ``sqrt(2 rho(|r|)) r / |r|`` so that a least-squares
solver minimises it: a badly segmented frame pulls with a bounded force instead of a quadratic one.

The estimate is chosen by ``estimator``: ``softgrip_jax.Geometric()`` (the paper's eq. 9) or
``softgrip_jax.Mechanics(config)`` (the spring-joint chain at equilibrium,
:mod:`softgrip_jax._mechanics`), by default ``Mechanics()`` as everywhere else; the residuals,
Jacobian and standard errors are those of the chosen estimate, differentiated through the
mechanics solve by implicit differentiation.

Parameters are named per finger (``"left.theta_entire"``, ``"right.base_offset"``); the registry
:data:`PARAMETERS` lists what can be fitted, each with the number of frame pairs it needs, the
estimates it affects, and how the solver's unknown maps to it:

- ``theta_entire`` (rad) and ``base_offset`` ([mm, mm]) are fitted as they are;
- ``stiffness_ratio`` (base-to-tip bending stiffness, > 0) is fitted as its logarithm u, ratio =
  exp(u): it stays positive, and a factor of two is the same step whether toward stiffer or softer;
- ``base_compliance`` (>= 0, in units of the finger's bending compliance) is fitted as its square
  root v, compliance = v^2: it stays >= 0, and the clamped base (compliance 0) is the ordinary point
  v = 0, where d(compliance)/dv = 2 v is finite (a logarithm would put it at minus infinity, and a
  logarithm with a floor would make the floor a tuning constant). Because v = 0 is a stationary
  point of anything that depends on v^2 only, a fit of the compliance that starts from exactly 0
  starts from :data:`COMPLIANCE_START` instead.

Both stiffness parameters only change the mechanics estimate (the geometric one ignores them), so
asking for them with ``Geometric()`` is an error. Internally
the solver's unknown is a PyTree ``{side: {parameter: value}}`` of every registered parameter, and
those not being fitted are held at their start values (their Jacobian columns are zero, which the
damped solve handles), so every choice of fitted parameters reuses one compilation. Frames are
stacked per SDF type and shape and padded to a multiple of :data:`FRAME_BUCKET` with masked copies,
so fits over similar numbers of frames reuse it too. The first fit in a process compiles; later fits
reuse the compilation.

After the solve: the standard error of each fitted parameter, ``sqrt(diag(sigma^2 (J^T J)^-1))``
with J the Jacobian of the robust residuals at the solution (the solver's own linearisation, so the
robust loss weights it: an outlying joint counts less) with respect to the parameters in their own
units (the solver's columns divided by the derivative of each transform above: the delta method,
so the stiffness ratio's standard error is in units of the ratio, not of its logarithm) and
``sigma^2 = sum r_rho^2 / (m - p)`` (m scalar residuals of the used frames, p fitted parameters);
from :data:`MIN_CLUSTERED_FRAMES` pairs on, the larger of that and the frame-clustered estimate
(:func:`_covariance`: a frame's joints share its measurement errors). A stiffness parameter whose
effect on the joints stays below the residuals gets a :class:`PoorlyDeterminedWarning`. And the
residual RMS (mm, of the raw joint distances) per frame and overall.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Literal, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float
from tqdm import tqdm

from softgrip_calib.one_frame import frame_keypoints, frame_measurement
from softgrip_calib.profile import SIDES, CalibrationProfile, FingerEntry, FitEntry
from softgrip_jax import (AbstractEstimator, AbstractSDF, ContactConfig, FingerFrame, FingerModel, SoftgripError,
                          Status, as_estimator, estimate_in_frame)
from softgrip_vision.frames import Frame, load_frame
from softgrip_vision.measure import MeasureSettings
from softgrip_vision.segmentation import SegmentationSettings

Loss = Literal["huber", "cauchy"]

#: Theta (rad) a fit starts from when nothing better is known.
NOMINAL_THETA = 0.5

#: Base compliance (units of the finger's bending compliance L / mean(k)) a fit of
#: ``base_compliance`` starts from when the start profile has 0 (a clamped base): the solver's
#: unknown is sqrt(compliance), whose derivative vanishes at 0, so the fit could not leave it. At
#: 0.01 the base turns by a hundredth of what the whole finger bends under the same moment.
COMPLIANCE_START = 0.01

#: Frames are padded (with masked copies) to a multiple of this, so that fits over similar numbers
#: of frame pairs share one compilation (every padded copy is evaluated at every step: a bucket much
#: larger than the usual few pairs multiplies the cost of a step).
FRAME_BUCKET = 8

#: The fit stops when an accepted step changes every joint residual by less than FIT_ATOL mm plus
#: FIT_RTOL of it (see :func:`_residual_change_norm`): 0.1 micrometre is far below what frames
#: resolve, and a tighter stop asks for more than the estimate's float32 joints carry.
FIT_RTOL = FIT_ATOL = 1e-4

#: With at least this many frame pairs, standard errors also allow for errors shared by the joints
#: of one frame (see :func:`_covariance`); with fewer, the frame-clustered estimate is too noisy.
MIN_CLUSTERED_FRAMES = 8

#: A stiffness parameter is reported as poorly determined (:class:`PoorlyDeterminedWarning`) when a
#: change of this fraction moves no joint of the used frames by as much as the residual RMS.
RESOLUTION_CHANGE = 0.1

# A calibration runs one fit per process: XLA's backend optimisations would lengthen its compile
# time (about doubling it) to speed up later fits, which one process does not run.
_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


class FitError(SoftgripError):
    """A least-squares calibration that cannot be done; the message says why and what to change."""


class NotConvergedError(FitError):
    """A least-squares fit that stopped before converging (its iteration cap, or a solver failure)."""


class SkippedFrameWarning(UserWarning):
    """A frame pair left out of the fit; the message names it and says why."""


class PoorlyDeterminedWarning(UserWarning):
    """A fitted parameter whose effect on the frames is below their residuals: its value rests on
    how the measurement errors happen to fall, more than its standard error says."""


@dataclass(frozen=True)
class Parameter:
    """A per-finger quantity the fit can adjust (a field of :class:`softgrip_calib.profile.FingerEntry`).

    Attributes:
        name: the field name, e.g. ``"theta_entire"``.
        shape: its shape (``()`` for a number, ``(2,)`` for [dx, dy]).
        min_frames: frame pairs needed before the fit can tell it from one pair's own noise.
        why: the reason for ``min_frames``, for the error message.
        transform: how the solver's unknown y maps to the value: ``"identity"`` (y), ``"log"``
            (exp(y): stays > 0) or ``"sqrt"`` (y^2: stays >= 0).
        methods: the names of the estimates (``estimator.name``) the value affects; None: every one.
    """

    name: str
    shape: tuple[int, ...]
    min_frames: int
    why: str = ""
    transform: Literal["identity", "log", "sqrt"] = "identity"
    methods: tuple[str, ...] | None = None


_STIFFNESS_WHY = ("a single pair's closure can be matched by trading Theta against the stiffness; pairs with the "
                  "object at different places along the fingers tell them apart")

#: Everything the fit can adjust, by name.
PARAMETERS: dict[str, Parameter] = {
    p.name: p for p in (
        Parameter("theta_entire", (), 1),
        Parameter("base_offset", (2,), 2, "from a single pair a base offset absorbs that pair's own keypoint "
                                          "error instead of a bias shared by all frames"),
        Parameter("stiffness_ratio", (), 2, _STIFFNESS_WHY, transform="log", methods=("mechanics",)),
        Parameter("base_compliance", (), 2, _STIFFNESS_WHY, transform="sqrt", methods=("mechanics",)),
    )
}


def _to_unknown(p: Parameter, value):
    """The solver's unknown of a parameter value (numpy, float64)."""
    value = np.asarray(value, np.float64)
    if p.transform == "log":
        return np.log(value)
    return np.sqrt(value) if p.transform == "sqrt" else value


def _from_unknown(p: Parameter, y, xp=jnp):
    """The parameter value of the solver's unknown (``xp``: jax.numpy, or numpy on the host)."""
    if p.transform == "log":
        return xp.exp(y)
    return y * y if p.transform == "sqrt" else y


def _transform_derivative(p: Parameter, y: np.ndarray) -> np.ndarray:
    """d(value)/d(unknown) at y (numpy)."""
    if p.transform == "log":
        return np.exp(y)
    return 2.0 * y if p.transform == "sqrt" else np.ones_like(y)


@dataclass(frozen=True, eq=False)
class Observation:
    """One open/closed frame pair, in millimetres in the gripper plane.

    Attributes:
        sdf: the object's signed distance in the open frame (an ``SDFGrid`` from its mask, or a
            ``PolygonSDF``); an SDF that is far everywhere when there is no object.
        bases: (2, 2) [left, right] finger bases seen in the open frame.
        observed: (2, N+1, 2) [left, right] observed joints of the closed fingers, base first.
        label: how reports and warnings name the pair.
        free_closure: True for the pair whose closed frame shows the gripper closed without an
            object (the one-frame calibration's data, eq. 4; see :func:`free_closure_observation`):
            the fit's report names it (``fit.free_closure``), so that what the fit did to the free
            closure can be checked. At most one per fit.
    """

    sdf: AbstractSDF
    bases: np.ndarray
    observed: np.ndarray
    label: str = "frame pair"
    free_closure: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.sdf, AbstractSDF):
            raise FitError(f"{self.label}: sdf must be a softgrip_jax SDF (SDFGrid or PolygonSDF), got "
                           f"{type(self.sdf).__name__}")
        bases, observed = np.asarray(self.bases, np.float64), np.asarray(self.observed, np.float64)
        if bases.shape != (2, 2):
            raise FitError(f"{self.label}: bases must be (2, 2) [left, right] base points in mm, got shape "
                           f"{bases.shape}")
        if observed.ndim != 3 or observed.shape[0] != 2 or observed.shape[1] < 2 or observed.shape[2] != 2:
            raise FitError(f"{self.label}: observed must be (2, N+1, 2) [left, right] joints in mm, got shape "
                           f"{observed.shape}")
        object.__setattr__(self, "bases", bases)
        object.__setattr__(self, "observed", observed)


def fit(
    observations: Sequence[Observation],
    start: CalibrationProfile,
    parameters: Sequence[str] = ("theta_entire",),
    *,
    loss: Loss = "huber",
    loss_scale_mm: float = 1.0,
    config: ContactConfig = ContactConfig(),
    estimator: AbstractEstimator | None = None,
    max_steps: int = 100,
    skipped: Sequence[dict[str, str]] = (),
    progress: bool = True,
    unconstrained: Literal["error", "hold"] = "error",
) -> CalibrationProfile:
    """Fit ``parameters`` of both fingers to the observations by robust least squares.

    Args:
        observations: the frame pairs.
        start: starting values, and everything that is not fitted (L, r, N, W, segmentation,
            camera). Both fingers must have the same ``n_links`` N, and every observation N+1
            joints per finger.
        parameters: names from :data:`PARAMETERS`, fitted for both fingers. ``stiffness_ratio``
            and ``base_compliance`` need the mechanics estimate.
        loss: ``"huber"`` (quadratic up to the scale, linear beyond) or ``"cauchy"`` (logarithmic
            beyond: ignores gross outliers more, but is not convex).
        loss_scale_mm: the scale c of the loss, mm (> 0); a very large value is plain least squares.
        config: the contact sweep's discretisation (as for the estimate).
        estimator: the estimate the residuals go through: ``Geometric()`` (eq. 9) or
            ``Mechanics(config)`` (the spring chain at equilibrium, solver settings ``config``);
            None: ``Mechanics()``, as everywhere else.
        max_steps: Levenberg-Marquardt iteration cap.
        skipped: pairs already left out upstream (``{"frame", "reason"}``), carried into the report.
        progress: show a progress bar on stderr. Its per-step report is a host callback: with
            ``progress=False`` the compiled solve has none and is kept by the persistent
            compilation cache (``softgrip_jax.enable_compilation_cache``).
        unconstrained: what to do with a parameter the residuals do not change with (e.g. the
            stiffness of a finger that touches no object): ``"error"`` raises a FitError naming it;
            ``"hold"`` keeps it at its start value, without a standard error.

    Returns:
        ``start`` with the fitted values and ``fit`` describing the fit: method ``"least-squares"``,
        the estimator's name (``fit.estimate_method``), the frames used, residual RMS (mm) per
        frame and overall, standard errors, skipped frames; and per frame the residual RMS at the
        start values (``fit.frame_start_residual_rms_mm``) and the fitted mean joint error at joint
        N // 2 and at the tip (``fit.frame_mid_error_mm``, ``fit.frame_tip_error_mm``), all mm; and
        ``fit.free_closure``, the label of the used observation marked ``free_closure`` (None
        without one).
        Pairs that cannot be used (non-finite input, or an invalid estimate at the start values:
        the open finger overlaps the object, its base lies outside the SDF grid, ...) are skipped
        with a :class:`SkippedFrameWarning`.

    Raises:
        FitError: unknown parameters or bad settings (including a stiffness parameter with
            ``Geometric()``), more than one observation marked ``free_closure``, no usable frame pair, fewer usable pairs than a parameter needs
            (under-determined: the message names it), a parameter the frames do not constrain at all
            (e.g. the stiffness when no finger touches an object), mismatched N, no convergence, or a
            fitted Theta outside [0, pi/2).

    Example (a pair without an object, whose closed fingers are PCC shapes of Theta 0.55 and 0.45
    rad; the fit starts from 0.5 and finds both):
        >>> import numpy as np
        >>> from softgrip_calib.one_frame import free_closure_joints
        >>> from softgrip_calib.profile import CalibrationProfile, FingerEntry, FitEntry
        >>> from softgrip_jax import PolygonSDF
        >>> entry = lambda theta: FingerEntry(52.0, theta, 4.0, 5, (0.0, 0.0))  # L, Theta, r, N, offset
        >>> bases = np.array([[-32.0, 0.0], [32.0, 0.0]])  # (left, right) in mm
        >>> true = {"left": entry(0.55), "right": entry(0.45)}
        >>> observed = np.stack([free_closure_joints(true[s], b, s) for s, b in zip(("left", "right"), bases)])
        >>> far = PolygonSDF.regular((1000.0, 1000.0), 1.0, n_vertices=3)  # no object within reach
        >>> start = CalibrationProfile(fingers={"left": entry(0.5), "right": entry(0.5)}, base_separation=64.0,
        ...     segmentation={}, camera={"name": "example", "intrinsics": None},
        ...     fit=FitEntry(method="one-frame", frames=["nominal"]))
        >>> from softgrip_jax import Geometric
        >>> fitted = fit([Observation(far, bases, observed, "pair 1")], start, estimator=Geometric(), progress=False)
        >>> [round(fitted.fingers[s].theta_entire, 3) for s in ("left", "right")], fitted.fit.method
        ([0.55, 0.45], 'least-squares')
    """
    names, estimator = _check_settings(parameters, loss, loss_scale_mm, max_steps, estimator)
    n_links = _common_n_links(start, observations)
    free = [obs.label for obs in observations if obs.free_closure]
    if len(free) > 1:
        raise FitError(f"{len(free)} frame pairs are marked as the free closure ({'; '.join(free)}): give one pair "
                       f"of the gripper closed without an object")
    skipped = [dict(s) for s in skipped]
    total = len(observations) + len(skipped)
    candidates = []
    for obs in observations:
        reason = _non_finite(obs)
        if reason is None:
            candidates.append(obs)
        else:
            skipped.append(_skip(obs.label, reason))
    _require_frames(candidates, names, skipped, total)

    bar = tqdm(total=max_steps, desc="least-squares fit (compiles on first use)", unit="step", file=sys.stderr,
               disable=not progress, leave=False)
    with bar, _reporting_to(bar), jax.enable_x64(True):
        y0, fixed, free = _unknowns(start, names)
        groups, index = _stack(candidates)
        out = _solve(y0, free, fixed, groups, jnp.asarray(loss_scale_mm, jnp.float64), n_links=n_links,
                     config=config, estimator=estimator, loss=loss, max_steps=max_steps,
                     progress=progress)
        flat, result, start_status, start_residuals, residuals, robust, jacobian = jax.tree.map(np.asarray, out)

    start_ok = (_per_frame(start_status, index) == Status.OK).all(axis=1)
    for obs, status in zip(candidates, _per_frame(start_status, index)):
        if not (status == Status.OK).all():
            skipped.append(_skip(obs.label, "the estimate at the start values is invalid: " + _describe(status)))
    used = [obs for obs, ok in zip(candidates, start_ok) if ok]
    _require_frames(used, names, skipped, total)
    if int(result) != _SUCCESSFUL:
        raise NotConvergedError(f"the least-squares fit did not converge within {max_steps} steps (optimistix result "
                       f"{int(result)}); raise max_steps, or start closer (e.g. from a one-frame calibration)")
    final = _per_frame(residuals, index)[start_ok]
    # The frame pair of each of the solver's residuals, flattened the way the solver's are.
    clusters = np.concatenate([np.broadcast_to((start_row + np.arange(len(g.real)))[:, None, None, None],
                                               g.observed.shape).ravel()
                               for start_row, g in zip(np.cumsum([0] + [len(g.real) for g in groups]), groups)])
    fitted = _report(start, names, flat, final, robust, jacobian, y0, [o.label for o in used], skipped, estimator.name,
                     clusters, hold=unconstrained == "hold")
    return _with_frame_report(fitted, _per_frame(start_residuals, index)[start_ok], final,
                              next((o.label for o in used if o.free_closure), None))


def profile_residuals(profile: CalibrationProfile, observations: Sequence[Observation], *,
                      estimator: AbstractEstimator | None = None,
                      config: ContactConfig = ContactConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Estimated minus observed joints of ``profile`` on ``observations``, as the fit sees them.

    Returns:
        (F, 2, N+1, 2) residuals in mm ([left, right] fingers, base first) and (F, 2) estimate
        statuses (``Status``), one row per observation in order; rows whose status is not OK are
        not meaningful. Evaluated in float64 with the fit's compiled residual function, so a
        held-out pair costs no compilation after a fit.
    """
    estimator = as_estimator(estimator, None, None)
    n_links = _common_n_links(profile, observations)
    with jax.enable_x64(True):
        y, fixed, _ = _unknowns(profile, ())
        groups, index = _stack(observations)
        residuals, status = jax.tree.map(np.asarray, _evaluate(y, fixed, groups, n_links, config, estimator))
    return _per_frame(residuals, index), _per_frame(status, index)


class PairOrderError(SoftgripError):
    """A frame pair given CLOSED OPEN instead of OPEN CLOSED (the "open" fingers curl more)."""


#: How much straighter (chord over arc length) the open frame's fingers must not be than the closed
#: frame's for a pair to count as swapped. Open fingers measure about 1.0, closed ones 0.9 and less;
#: two frames of the same state differ by measuring noise of a few thousandths.
PAIR_ORDER_MARGIN = 0.01


def check_pair_order(open_keypoints, closed_keypoints, label: str) -> None:
    """Refuse a pair whose "open" frame shows the fingers more curled than its "closed" frame.

    Raises:
        PairOrderError: names the pair, both frames' straightness and the fix.
    """
    from softgrip_vision.plausibility import straightness

    opened, closed = straightness(open_keypoints), straightness(closed_keypoints)
    if np.isfinite(opened) and np.isfinite(closed) and opened < closed - PAIR_ORDER_MARGIN:
        raise PairOrderError(f"{label}: the pair looks swapped: the fingers of the first ('open') frame are more "
                             f"curled (chord/arc {opened:.3f}) than those of the second ('closed') frame "
                             f"({closed:.3f}); give each pair as OPEN CLOSED")


def observations_from_frames(
    open_frame: Frame,
    closed_frame: Frame,
    settings: SegmentationSettings | None,
    n_links: int,
    label: str = "frame pair",
    *,
    measure: MeasureSettings | None = None,
) -> Observation:
    """The :class:`Observation` of a pair of frames, through the vision pipeline.

    The open frame gives both finger bases and the object's signed-distance grid (far everywhere
    without an object; the outline taken at the depth of the object's front face); the closed
    frame gives both fingers' centrelines divided into ``n_links`` equal arc lengths (split at the
    open frame's centre line when its fingertips touch). ``measure`` says how the fingers are
    measured (a profile's ``softgrip_vision`` settings; defaults when None).

    Raises:
        SoftgripError: segmentation, depth or keypoint failures (the message names what to adjust).

    Example (the sample circle scene, N = 20):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> obs = observations_from_frames(load_frame(data / "circle_open"), load_frame(data / "circle_closed"),
        ...                                None, 20)
        >>> obs.bases.shape, obs.observed.shape  # (left, right) bases; N+1 closed joints each; mm
        ((2, 2), (2, 21, 2))
        >>> round(float(obs.bases[1, 0] - obs.bases[0, 0]))  # the base separation W, mm
        64
    """
    return _measured_pair(open_frame, closed_frame, settings, n_links, label, measure)[0]


def _measured_pair(open_frame: Frame, closed_frame: Frame, settings: SegmentationSettings | None, n_links: int,
                   label: str, measure: MeasureSettings | None, free_closure: bool = False):
    """(the pair's Observation, the closed frame's measurement)."""
    opened = frame_measurement(open_frame, settings, measure)
    closed = frame_measurement(closed_frame, settings, measure, center_hint=opened.segmentation.center_column)
    check_pair_order(opened.keypoints, closed.keypoints, label)
    # Both frames' millimetres are their own fitted planes: the same plane when the camera stayed.
    observation = Observation(
        sdf=opened.object_sdf(open_frame),
        bases=np.stack([f.base_mm for f in opened.keypoints]),
        observed=np.stack([f.observed_mm(n_links) for f in closed.keypoints]),
        label=label,
        free_closure=free_closure,
    )
    return observation, closed


def free_closure_observation(
    open_frame: Frame,
    closed_frame: Frame,
    settings: SegmentationSettings | None,
    n_links: int,
    label: str = "calibration pair",
    *,
    measure: MeasureSettings | None = None,
    closed_name: str = "the closed frame",
) -> Observation:
    """The :class:`Observation` of a calibration pair: an open frame and a frame of the gripper
    closed without an object (the one-frame calibration's data, eq. 4), marked ``free_closure``.

    In a fit over pairs with objects, this pair keeps Theta from bending to make up for errors in
    L, r or the bases that the object pairs cannot tell apart from Theta: the free closure then
    pulls back. The fit reports it as ``fit.free_closure``, with its residual at the start values
    next to the fitted one.

    Args:
        open_frame: the frame of the open gripper.
        closed_frame: the frame of the gripper closed without an object.
        settings: as for :func:`observations_from_frames`.
        n_links: as for :func:`observations_from_frames`.
        measure: as for :func:`observations_from_frames`.
        label: how reports and warnings name the pair.
        closed_name: how the error names the closed frame (e.g. its folder).

    Raises:
        SoftgripError: the closed frame shows an object (the message names ``closed_name``), or
            the vision pipeline fails on either frame.

    Example (the sample calibration pair; N = 20):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> obs = free_closure_observation(load_frame(data / "calib_open"), load_frame(data / "calib_closed"),
        ...                                None, 20, "calib")
        >>> obs.free_closure, obs.observed.shape  # (left, right), N + 1 joints, mm
        (True, (2, 21, 2))
        >>> free_closure_observation(load_frame(data / "circle_open"), load_frame(data / "circle_closed"), None, 20,
        ...                          closed_name="circle_closed")
        Traceback (most recent call last):
        ...
        softgrip_base.errors.SoftgripError: circle_closed shows an object (... px): ...
    """
    observation, closed = _measured_pair(open_frame, closed_frame, settings, n_links, label, measure, True)
    if closed.segmentation.object.any():
        raise SoftgripError(
            f"{closed_name} shows an object ({int(closed.segmentation.object.sum())} px): the free-closure pair needs "
            f"the gripper closed without touching anything; give a frame closed without the object (or raise the "
            f"segmentation's object_min_saturation / min_object_px if that is not an object)")
    return observation


def load_observations(
    pairs: Sequence[tuple[str | Path, str | Path]],
    settings: SegmentationSettings | None,
    n_links: int,
    progress: bool = True,
    *,
    measure: MeasureSettings | None = None,
) -> tuple[list[Observation], list[dict[str, str]]]:
    """Observations of (open, closed) frame folders; pairs that fail are skipped with a warning.
    ``measure``: how the fingers are measured (see :func:`observations_from_frames`).

    Returns:
        The observations (labelled ``"OPEN + CLOSED"``) and the skipped pairs
        (``{"frame", "reason"}``), for :func:`fit`'s ``skipped``.

    Example (the second pair's open folder does not exist, so that pair is skipped):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> pairs = [(data / "circle_open", data / "circle_closed"), (data / "nowhere", data / "circle_closed")]
        >>> observations, skipped = load_observations(pairs, None, 20, progress=False)
        >>> len(observations), len(skipped), "does not exist" in skipped[0]["reason"]
        (1, 1, True)
    """
    observations, skipped = [], []
    for open_path, closed_path in tqdm(pairs, desc="reading frame pairs", unit="pair", file=sys.stderr,
                                       disable=not progress, leave=False):
        label = f"{open_path} + {closed_path}"
        try:
            observations.append(observations_from_frames(load_frame(open_path), load_frame(closed_path),
                                                         settings, n_links, label, measure=measure))
        except PairOrderError:
            raise  # a mistake in the command, not in one pair's data: never skipped silently
        except SoftgripError as err:
            skipped.append(_skip(label, str(err)))
    return observations, skipped


def start_from_open_frame(
    open_frame: Frame,
    n_links: int,
    settings: SegmentationSettings | None = None,
    theta_entire: float = NOMINAL_THETA,
    camera_name: str = "unspecified",
    *,
    measure: MeasureSettings | None = None,
) -> CalibrationProfile:
    """Starting values for :func:`fit` from an open frame alone: L (eq. 5), r and the base
    separation W from its fingers, and a nominal Theta for both fingers.

    Raises:
        SoftgripError: the vision pipeline fails on the frame (the message names what to adjust).

    Example (L in mm, Theta in rad):
        >>> from pathlib import Path
        >>> import softgrip_calib
        >>> from softgrip_vision.frames import load_frame
        >>> data = Path(softgrip_calib.__file__).resolve().parents[1] / "data"  # the sample frames
        >>> start = start_from_open_frame(load_frame(data / "calib_open"), 20)
        >>> round(start.fingers["left"].length), start.fingers["left"].theta_entire
        (52, 0.5)
    """
    _, _, fingers = frame_keypoints(open_frame, settings, measure)
    entries = {side: FingerEntry(length=f.length_mm, theta_entire=theta_entire,
                                 half_thickness=f.half_thickness_mm, n_links=n_links)
               for side, f in zip(SIDES, fingers)}
    return CalibrationProfile(
        fingers=entries, base_separation=float(np.hypot(*(fingers[1].base_mm - fingers[0].base_mm))),
        segmentation=(settings or SegmentationSettings()).to_dict(),
        camera={"name": camera_name, "intrinsics": open_frame.intrinsics.to_dict()},
        fit=FitEntry(method="least-squares", frames=[]),
        vision=(measure or MeasureSettings()).to_dict(),
    )


# ---------------------------------------------------------------------------------------------
# Checks on the host


def _check_settings(parameters: Sequence[str], loss: str, scale: float, max_steps: int,
                    estimator: object) -> tuple[list[str], AbstractEstimator]:
    """The parameter names, without repeats, and the estimator (:func:`softgrip_jax.as_estimator`)."""
    names = list(dict.fromkeys(parameters))
    unknown = [n for n in names if n not in PARAMETERS]
    if not names or unknown:
        raise FitError(f"unknown parameter(s) {', '.join(map(repr, unknown)) or '(none given)'}; the fit can "
                       f"adjust: {', '.join(PARAMETERS)}")
    try:
        estimator = as_estimator(estimator)
    except SoftgripError as err:  # not an estimator
        raise FitError(str(err)) from None
    unused = [n for n in names if (methods := PARAMETERS[n].methods) is not None and estimator.name not in methods]
    if unused:
        raise FitError(f"{', '.join(unused)} only affect(s) the mechanics estimate, so {estimator.name!r} cannot fit "
                       f"them: fit with estimator=Mechanics() (softgrip calibrate --fit ... --method mechanics), or "
                       f"leave them out")
    if loss not in ("huber", "cauchy"):
        raise FitError(f"loss must be 'huber' or 'cauchy', got {loss!r}")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise FitError(f"loss_scale_mm must be a finite number of mm > 0, got {scale!r}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise FitError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    return names, estimator


def _common_n_links(start: CalibrationProfile, observations: Sequence[Observation]) -> int:
    n_links = {start.fingers[side].n_links for side in SIDES}
    if len(n_links) != 1:
        raise FitError(f"the fit needs both fingers to have the same n_links; the start profile has "
                       f"{start.fingers['left'].n_links} (left) and {start.fingers['right'].n_links} (right)")
    (n,) = n_links
    for obs in observations:
        if obs.observed.shape[1] != n + 1:
            raise FitError(f"{obs.label}: {obs.observed.shape[1]} observed joints per finger, but the start "
                           f"profile has n_links = {n} (N + 1 = {n + 1} joints); divide the closed fingers "
                           f"into n_links parts")
    return n


def _non_finite(obs: Observation) -> str | None:
    """Why an observation cannot be used before any estimate, or None."""
    for what, values in (("finger bases", obs.bases), ("observed joints", obs.observed)):
        bad = ~np.isfinite(values)
        if bad.any():
            side = SIDES[int(np.argwhere(bad)[0][0])]
            return f"non-finite {what} of the {side} finger"
    if not all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree.leaves(obs.sdf)):
        return "non-finite values in the object's signed distance"
    return None


def _skip(label: str, reason: str) -> dict[str, str]:
    warnings.warn(f"{label}: skipped: {reason}", SkippedFrameWarning, stacklevel=3)
    return {"frame": label, "reason": reason}


def _require_frames(frames: Sequence[Observation], names: Sequence[str], skipped: Sequence[dict[str, str]],
                    total: int) -> None:
    """Raise unless there are enough usable frame pairs for every parameter."""
    if not frames:
        reasons = "; ".join(f"{s['frame']}: {s['reason']}" for s in skipped) or "none given"
        raise FitError(f"no usable frame pair (of {total}): {reasons}")
    short = [PARAMETERS[n] for n in names if PARAMETERS[n].min_frames > len(frames)]
    if short:
        fitted = ", ".join(f"{side}.{p.name}" for p in short for side in SIDES)
        need = max(p.min_frames for p in short)
        why = "; ".join(p.why for p in short if p.why)
        raise FitError(f"a fit of {fitted} from {len(frames)} usable frame pair(s) is under-determined: it needs "
                       f"at least {need} ({why}); add frame pairs, or fit only theta_entire")


# ---------------------------------------------------------------------------------------------
# The unknowns and the stacked frames


def _unknowns(start: CalibrationProfile, names: Sequence[str]):
    """(y0, fixed, free), each ``{side: {field: array}}``: start values of every registered parameter
    (float64), the finger values that are never fitted, and which parameters are fitted (bool)."""
    numbers = np.hstack([np.ravel(v) for side in SIDES for v in dataclasses.astuple(start.fingers[side])])
    if not np.isfinite(numbers.astype(np.float64)).all():
        raise FitError("the start profile has non-finite finger values")
    def start_value(side, p):
        value = getattr(start.fingers[side], p.name)
        if p.transform == "sqrt" and p.name in names and value == 0.0:
            value = COMPLIANCE_START  # sqrt(0) is a stationary point of the fit (see the module docstring)
        return jnp.asarray(_to_unknown(p, value)).reshape(p.shape)

    y0 = {side: {p.name: start_value(side, p) for p in PARAMETERS.values()} for side in SIDES}
    fixed = {side: {name: jnp.asarray(getattr(start.fingers[side], name), jnp.float64)
                    for name in ("length", "half_thickness")} for side in SIDES}
    free = {side: {p.name: jnp.full(p.shape, p.name in names) for p in PARAMETERS.values()} for side in SIDES}
    return y0, fixed, free


class _Frames(eqx.Module):
    """Frame pairs stacked along a leading axis F (padded copies have ``real`` False)."""

    sdf: AbstractSDF
    bases: Float[Array, "f 2 2"]
    observed: Float[Array, "f 2 j 2"]
    real: Bool[Array, " f"]


def _stack(observations: Sequence[Observation]) -> tuple[list[_Frames], list[tuple[int, int]]]:
    """Group observations by SDF type and shapes, stack each group in float64 and pad it to a
    multiple of FRAME_BUCKET. Returns the groups and, per observation, (group, row)."""
    def signature(obs):
        leaves, treedef = jax.tree.flatten(obs.sdf)
        return treedef, tuple(np.shape(leaf) for leaf in leaves)

    keys: dict[Any, list[int]] = {}
    for i, obs in enumerate(observations):
        keys.setdefault(signature(obs), []).append(i)
    groups, index = [], [(0, 0)] * len(observations)
    for g, members in enumerate(keys.values()):
        padded = members + [members[0]] * (-len(members) % FRAME_BUCKET)
        rows = [observations[i] for i in padded]
        groups.append(_Frames(
            sdf=jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v, jnp.float64) for v in x]), *[o.sdf for o in rows]),
            bases=jnp.asarray(np.stack([o.bases for o in rows])),
            observed=jnp.asarray(np.stack([o.observed for o in rows])),
            real=jnp.asarray(np.arange(len(padded)) < len(members)),
        ))
        for row, i in enumerate(members):
            index[i] = (g, row)
    return groups, index


def _per_frame(per_group: Sequence[np.ndarray], index: Sequence[tuple[int, int]]) -> np.ndarray:
    """Rows of per-group arrays, one per observation, in observation order."""
    return np.stack([per_group[g][row] for g, row in index])


# ---------------------------------------------------------------------------------------------
# The compiled solve


def _finger_residuals(values, fixed, frames: _Frames, n_links: int, config: ContactConfig,
                      estimator: AbstractEstimator):
    """Estimated minus observed joints (F, 2, J, 2) mm and estimate statuses (F, 2) of one group.
    ``values`` are the solver's unknowns (see :data:`PARAMETERS` for their transforms)."""
    natural = {side: {name: _from_unknown(PARAMETERS[name], v) for name, v in values[side].items()} for side in SIDES}
    fingers = jax.tree.map(lambda *v: jnp.stack(v), *({**natural[side], **fixed[side]} for side in SIDES))
    handedness = jnp.array([1.0, -1.0])

    def one_finger(p, hand, sdf, base, observed):
        finger = FingerModel(length=p["length"], theta_entire=p["theta_entire"], half_thickness=p["half_thickness"],
                             n_links=n_links, stiffness_ratio=p["stiffness_ratio"],
                             base_compliance=p["base_compliance"])
        frame = FingerFrame(origin=base + p["base_offset"], angle=jnp.zeros_like(hand), handedness=hand)
        est = estimate_in_frame(finger, sdf, frame, config, estimator=estimator)
        return est.joints - observed, est.status

    def one_frame(sdf, bases, observed):
        return jax.vmap(one_finger, in_axes=(0, 0, None, 0, 0))(fingers, handedness, sdf, bases, observed)

    return jax.vmap(one_frame)(frames.sdf, frames.bases, frames.observed)


def _robust(residuals: Float[Array, "*b 2"], scale: Float[Array, ""], loss: Loss) -> Float[Array, "*b 2"]:
    """Joint residuals r rescaled to sqrt(2 rho(|r|)) r / |r|, so their squares sum to 2 rho."""
    e2 = jnp.sum(residuals**2, axis=-1, keepdims=True)
    if loss == "huber":
        far = e2 > scale**2
        e = jnp.sqrt(jnp.where(far, e2, 4.0 * scale**2))
        factor = jnp.where(far, jnp.sqrt(scale * (2.0 * e - scale)) / e, 1.0)
    else:
        u = e2 / scale**2
        small = u < 1e-12
        u_safe = jnp.where(small, 1.0, u)
        factor = jnp.where(small, 1.0 - 0.25 * u, jnp.sqrt(jnp.log1p(u_safe) / u_safe))
    return factor * residuals


def _residual_change_norm(tree) -> Array:
    """The norm optimistix's Levenberg-Marquardt judges convergence with, on a scaled change of the
    unknowns (a dict ``{side: {name: value}}``) or of the residuals (a list per frame group): the
    largest residual change, and 0 for the unknowns. A step that moves no joint by more than the
    tolerance has converged whatever it moves the unknowns by: along a direction the pairs hardly
    constrain (a stiffness ratio of a finger that barely touches), the unknowns would otherwise keep
    drifting in ever smaller steps of the loss until the iteration cap. Such a parameter gets a large
    standard error and a PoorlyDeterminedWarning instead."""
    return jnp.zeros(()) if isinstance(tree, dict) else optx.max_norm(tree)


def _report_step(**info) -> None:
    """optimistix's per-step hook: forward the step count and loss to the active progress bar."""
    jax.debug.callback(_tick, info["num_steps"][1], info["loss_last_accepted_step"][1])


# The solve is compiled once, so its host callback cannot close over one call's progress bar: it
# reports to the innermost bar that a running fit has registered here.
_ACTIVE_BARS: list[tqdm] = []


def _tick(step, loss) -> None:
    if _ACTIVE_BARS:
        bar = _ACTIVE_BARS[-1]
        bar.n = int(step) + 1
        bar.set_postfix_str(f"robust loss {float(loss):.4g}", refresh=True)


@contextmanager
def _reporting_to(bar: tqdm) -> Iterator[None]:
    _ACTIVE_BARS.append(bar)
    try:
        yield
    finally:
        _ACTIVE_BARS.remove(bar)


@partial(jax.jit, static_argnames=("n_links", "config", "estimator"))
def _evaluate(values, fixed, groups: list[_Frames], n_links: int, config: ContactConfig, estimator: AbstractEstimator):
    """Raw residuals (F, 2, J, 2) and statuses (F, 2) of every group. Jitted on its own so that the
    solve's several traces of it (start check, Jacobian) reuse one trace."""
    out = [_finger_residuals(values, fixed, g, n_links, config, estimator) for g in groups]
    return [r for r, _ in out], [s for _, s in out]


@partial(jax.jit, static_argnames=("n_links", "config", "estimator", "loss", "max_steps", "progress"),
         compiler_options=_COMPILER_OPTIONS)
def _solve(y0, free, fixed, groups: list[_Frames], scale, *, n_links: int, config: ContactConfig,
           estimator: AbstractEstimator, loss: Loss, max_steps: int, progress: bool = False):
    """Robust Levenberg-Marquardt from ``y0`` over the frames whose estimates are valid at ``y0``.

    Returns (flattened solution, optimistix result code, estimate statuses and raw residuals at the
    start (per group, (F, 2) and (F, 2, J, 2)), raw residuals at the solution (per group,
    (F, 2, J, 2)), robust residuals at the solution flattened (M,), and their Jacobian (M, P) with
    respect to the flattened unknowns).
    """
    def with_fixed(y):
        return jax.tree.map(lambda v, v0, f: jnp.where(f, v, v0), y, y0, free)

    @jax.custom_jvp
    def residuals(y):
        return _evaluate(y, fixed, groups, n_links, config, estimator)[0]

    @residuals.defjvp
    def residuals_jvp(primals, tangents):
        # Few unknowns and many residuals: one forward-mode Jacobian per linearisation, so that the
        # solver's linear operator is a small matrix (cheaper to compile than a linearised estimate).
        (y,), (dy,) = primals, tangents
        jac, r = jax.jacfwd(lambda z: (residuals.fun(z),) * 2, has_aux=True)(y)
        dy_leaves = jax.tree.leaves(dy)
        return r, [sum(jnp.tensordot(j, d, axes=d.ndim) for j, d in zip(jax.tree.leaves(jg), dy_leaves))
                   for jg in jac]

    start_residuals, start_status = _evaluate(y0, fixed, groups, n_links, config, estimator)
    usable = [g.real & jnp.all(s == Status.OK, axis=-1) for g, s in zip(groups, start_status)]

    def objective(y, args):
        raw = residuals(with_fixed(y))
        return [jnp.where(u[:, None, None, None], _robust(r, scale, loss), 0.0) for u, r in zip(usable, raw)], raw

    # The progress hook is a host callback, and a program with one never enters the persistent
    # compilation cache: it is compiled in only when a progress bar is shown.
    solver: optx.LevenbergMarquardt[Any, Any, Any] = optx.LevenbergMarquardt(
        rtol=FIT_RTOL, atol=FIT_ATOL, norm=_residual_change_norm, verbose=_report_step if progress else False)
    solution: optx.Solution[Any, Any] = optx.least_squares(objective, solver, y0, has_aux=True, max_steps=max_steps,
                                                           throw=False)
    # The solver's state holds the residuals and the linearisation at the last accepted step: the solution.
    robust = ravel_pytree(solution.state.f_info.residual)[0]
    return (ravel_pytree(solution.value)[0], solution.result._value, start_status, start_residuals,
            solution.state.aux, robust, solution.state.f_info.jac.as_matrix())


# ---------------------------------------------------------------------------------------------
# The report


# (cast: equinox turns the class's message strings into items at runtime; its types still say str)
_SUCCESSFUL = int(cast(optx.RESULTS, optx.RESULTS.successful)._value)


def _describe(status: np.ndarray) -> str:
    """Statuses (2,) of the [left, right] estimates, as text naming the invalid ones."""
    return ", ".join(f"{side} finger {Status(int(s)).name}" for side, s in zip(SIDES, status) if s != Status.OK)


def _columns(y0) -> list[tuple[str, str]]:
    """(side, parameter) of each entry of the flattened unknowns, in ``ravel_pytree`` order."""
    paths = jax.tree_util.tree_flatten_with_path(y0)[0]
    return [(path[0].key, path[1].key) for path, leaf in paths for _ in range(int(np.size(leaf)))]


def _covariance(jac: np.ndarray, robust: np.ndarray, clusters: np.ndarray, m: int, frames: int) -> np.ndarray:
    """Covariance (P, P) of the fitted values from the Jacobian ``jac`` (M, P) of the robust
    residuals ``robust`` (M,) at the solution; ``clusters`` (M,) the frame pair of each residual,
    ``m`` the number of scalar residuals of the ``frames`` used pairs.

    The textbook estimate ``sigma^2 (J^T J)^-1`` treats every joint coordinate as an independent
    measurement. Vision's errors are not: a base point, a finger's measured length or the outline's
    offset moves every joint of a frame together, and then that estimate is several times too
    small. With :data:`MIN_CLUSTERED_FRAMES` pairs or more, each parameter's variance is the larger
    of it and the frame-clustered sandwich ``B (sum_f J_f^T r_f r_f^T J_f) B G / (G - 1)``,
    ``B = (J^T J)^-1`` over G pairs (errors independent between pairs, any correlation within one).
    Neither sees an error every frame shares."""
    bread = np.linalg.inv(jac.T @ jac)
    covariance = np.sum(robust**2) / (m - jac.shape[1]) * bread
    if frames < MIN_CLUSTERED_FRAMES:
        return covariance
    scores = np.stack([jac[clusters == c].T @ robust[clusters == c] for c in np.unique(clusters)])  # (G', P)
    clustered = bread @ (scores.T @ scores) @ bread * frames / (frames - 1)
    scale = np.sqrt(np.maximum(np.diag(clustered), np.diag(covariance)) / np.diag(covariance))
    return covariance * np.outer(scale, scale)


def _warn_if_poorly_determined(jac: np.ndarray, columns: list[tuple[str, str]],
                               values: dict[tuple[str, str], list[float]], residuals: np.ndarray) -> None:
    """Warn for each fitted stiffness parameter whose :data:`RESOLUTION_CHANGE` moves no joint of
    the used frames by the residual RMS. ``jac`` (M, P) in the parameters' own units, its columns
    named by ``columns``; ``residuals`` (F, 2, J, 2) mm."""
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=-1))))
    for (side, name), column in zip(columns, jac.T):
        if name not in ("stiffness_ratio", "base_compliance"):
            continue
        value = values[(side, name)][0]
        change = RESOLUTION_CHANGE * (value if name == "stiffness_ratio" else max(value, COMPLIANCE_START))
        largest = float(np.max(np.hypot(*column.reshape(-1, 2).T))) * change
        if largest < rms:
            warnings.warn(PoorlyDeterminedWarning(
                f"{side}.{name} = {value:.3f} is poorly determined by these frame pairs: changing it by "
                f"{100 * RESOLUTION_CHANGE:.0f} % moves no joint by more than {largest:.3f} mm, less than the residual "
                f"RMS {rms:.3f} mm, so measurement errors shared along a finger can move it far more than its standard "
                f"error says. Add pairs whose object presses on the outer half of the fingers, or keep the stiffness "
                f"from the fingers' design"), stacklevel=4)


def _report(start: CalibrationProfile, names: Sequence[str], flat: np.ndarray, residuals: np.ndarray,
            robust: np.ndarray, jacobian: np.ndarray, y0, labels: list[str],
            skipped: list[dict[str, str]], estimate_name: str, clusters: np.ndarray,
            hold: bool = False) -> CalibrationProfile:
    """The fitted profile: values, residual RMS per frame and overall, standard errors.

    ``residuals`` (F, 2, J, 2) are the raw residuals of the F used frames; ``robust`` (M,) and
    ``jacobian`` (M, P) the solver's residuals (zero for unused frames) and their Jacobian with
    respect to the solver's unknowns ``flat`` (P,); ``clusters`` (M,) the frame pair of each.
    """
    columns = _columns(y0)
    fitted = [k for k, (_, name) in enumerate(columns) if name in names]
    values: dict[tuple[str, str], list[float]] = {}
    for (side, name), v in zip(columns, flat.tolist()):
        values.setdefault((side, name), []).append(float(_from_unknown(PARAMETERS[name], v, np)))

    distances = np.sqrt(np.sum(residuals**2, axis=-1))  # (F, 2, J) mm
    # The Jacobian with respect to the values in their own units (chain rule through each transform).
    derivative = np.array([_transform_derivative(PARAMETERS[columns[k][1]], flat[k]) for k in fitted])
    # (A derivative of exactly 0, the square-root unknown landing exactly on 0, does not happen from
    # COMPLIANCE_START in floating point; its column would then read as unconstrained below.)
    jac = jacobian[:, fitted] / np.where(derivative == 0.0, 1.0, derivative)
    norms = np.linalg.norm(jacobian[:, fitted], axis=0)
    flat_columns = [columns[k] for k, norm in zip(fitted, norms) if not norm > 0.0]
    if flat_columns and hold:  # held at their start values: the solver cannot have moved them
        keep = [i for i, k in enumerate(fitted) if columns[k] not in flat_columns]
        fitted, jac = [fitted[i] for i in keep], jac[:, keep]
    elif flat_columns:
        what = ", ".join(sorted({f"{side}.{name}" for side, name in flat_columns}))
        hint = (" (the stiffness only shows where a finger touches an object: add pairs whose closed fingers "
                "wrap an object)" if any(name in ("stiffness_ratio", "base_compliance") for _, name in flat_columns)
                else "")
        raise FitError(f"the frame pairs do not constrain {what}: the residuals do not change with it{hint}; "
                       f"add frame pairs, or do not fit it")
    covariance = _covariance(jac, robust, clusters, residuals.size, residuals.shape[0])
    _warn_if_poorly_determined(jac, [columns[k] for k in fitted], values, residuals)
    errors: dict[tuple[str, str], list[float]] = {}
    for k, se in zip(fitted, np.sqrt(np.diag(covariance)).tolist()):
        errors.setdefault(columns[k], []).append(se)

    fingers = {}
    for side in SIDES:
        update: dict[str, Any] = {}
        for name in names:
            v = values[(side, name)]
            update[name] = v[0] if PARAMETERS[name].shape == () else tuple(v)
        theta = update.get("theta_entire", start.fingers[side].theta_entire)
        if not 0.0 <= theta < math.pi / 2:
            raise FitError(f"the fitted Theta of the {side} finger is {theta:.4f} rad, outside [0, pi/2): the frame "
                           f"pairs do not look like closures of this gripper (are open and closed swapped?)")
        fingers[side] = dataclasses.replace(start.fingers[side], **update)
    standard_errors = {f"{side}.{name}": (se[0] if PARAMETERS[name].shape == () else se)
                       for (side, name), se in errors.items()}
    return dataclasses.replace(start, fingers=fingers, fit=FitEntry(
        method="least-squares", estimate_method=estimate_name, frames=labels,
        residual_rms_mm=float(np.sqrt(np.mean(distances**2))),
        frame_residual_rms_mm=np.sqrt(np.mean(distances**2, axis=(1, 2))).tolist(),
        standard_errors=standard_errors, skipped=skipped))


def _with_frame_report(profile: CalibrationProfile, start_residuals: np.ndarray, residuals: np.ndarray,
                       free_closure: str | None) -> CalibrationProfile:
    """``profile`` with the per-frame report: residual RMS at the start values, and mean fitted
    joint error at joint N // 2 and at the tip, from the raw residuals (F, 2, J, 2) mm of the used
    frames at the start and at the solution; and the free-closure pair's label (or None)."""
    start_rms = np.sqrt(np.mean(np.sum(start_residuals**2, axis=-1), axis=(1, 2)))  # (F,) mm
    distances = np.sqrt(np.sum(residuals**2, axis=-1))  # (F, 2, J) mm
    n_links = distances.shape[-1] - 1
    return dataclasses.replace(profile, fit=dataclasses.replace(
        profile.fit, free_closure=free_closure, frame_start_residual_rms_mm=start_rms.tolist(),
        frame_mid_error_mm=distances[:, :, n_links // 2].mean(axis=1).tolist(),
        frame_tip_error_mm=distances[:, :, n_links].mean(axis=1).tolist()))
