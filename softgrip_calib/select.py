"""Which stiffness model the frame pairs support: nested models, judged on held-out pairs.

A real soft finger is often stiffer at its base than at its tip, and sits in a clamp that gives a
little; the mechanics estimate models both (``stiffness_ratio`` and ``base_compliance`` of
:class:`softgrip_jax.FingerModel`), but more parameters also fit more of the frames' measurement
errors. :func:`fit_stiffness_model` lets the frames decide between the nested models of
:data:`STIFFNESS_MODELS`:

1. ``uniform``: a finger of uniform bending stiffness, clamped at its base (the paper's finger);
2. ``stiffness ratio``: + the base-to-tip stiffness ratio of each finger;
3. ``stiffness ratio + base compliance``: + a rotational spring at each finger's base.

Each model is fitted to all pairs (:func:`softgrip_calib.fit.fit`), each richer one starting from the fit of
the one before it (nested: the simpler model's solution is a point of the richer model, so the
richer fit starts where the simpler one ended). Each is then judged by leave-one-pair-out
prediction: for every pair with an object, the model is fitted to the other pairs and predicts the
left-out one; the held-out error is the RMS over those predictions of the joint distances (mm). A
richer model is chosen only when it predicts the held-out pairs better than the model chosen so far
by at least :data:`MIN_GAIN_MM` and :data:`MIN_GAIN_FRACTION` of its error: below that, the gain is
within what a different draw of the measurement errors would change, and the simpler model is
kept (the one-standard-error habit of cross-validation, with a fixed margin because three or four
folds give no usable standard error).

The free-closure pair (the gripper closed without an object) is never left out: it does not depend
on the stiffness, and it holds Theta.

A model whose fit does not converge, or that the pairs cannot determine, is reported with the
reason and not chosen; the fit then returns the richest model that did converge and says what more
data would allow. Only when even the uniform model fails is a :class:`softgrip_calib.fit.FitError` raised.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from softgrip_calib.fit import FitError, NotConvergedError, Observation, fit, profile_residuals
from softgrip_calib.profile import CalibrationProfile
from softgrip_jax import AbstractEstimator, ContactConfig, Status, as_estimator


@dataclass(frozen=True)
class StiffnessModel:
    """A stiffness model: its name and the stiffness parameters it fits (beyond Theta)."""

    name: str
    parameters: tuple[str, ...]


#: The nested stiffness models, simplest first.
STIFFNESS_MODELS: tuple[StiffnessModel, ...] = (
    StiffnessModel("uniform", ()),
    StiffnessModel("stiffness ratio", ("stiffness_ratio",)),
    StiffnessModel("stiffness ratio + base compliance", ("stiffness_ratio", "base_compliance")),
)

#: A richer model must lower the held-out error by at least this many mm ...
MIN_GAIN_MM = 0.02
#: ... and by at least this fraction of the held-out error of the model chosen so far.
MIN_GAIN_FRACTION = 0.1

#: Pairs with an object needed to judge a model on held-out pairs (one left out, the rest fitted).
MIN_OBJECT_PAIRS = 2


def fit_stiffness_model(
    observations: Sequence[Observation],
    start: CalibrationProfile,
    parameters: Sequence[str] = ("theta_entire",),
    *,
    estimator: AbstractEstimator | None = None,
    config: ContactConfig = ContactConfig(),
    max_steps: int = 100,
    skipped: Sequence[dict[str, str]] = (),
    progress: bool = True,
    **fit_options,
) -> CalibrationProfile:
    """Fit ``parameters`` plus the stiffness model the pairs support (see the module docstring).

    Args:
        observations: as for :func:`softgrip_calib.fit.fit`.
        start: as for :func:`softgrip_calib.fit.fit`.
        config: as for :func:`softgrip_calib.fit.fit`.
        max_steps: as for :func:`softgrip_calib.fit.fit`.
        skipped: as for :func:`softgrip_calib.fit.fit`.
        progress: as for :func:`softgrip_calib.fit.fit`.
        parameters: what every model fits (``theta_entire``, optionally ``base_offset``); the
            stiffness parameters are added per model.
        estimator: the mechanics estimate (``Mechanics(config)``); None: ``Mechanics()``. The
            geometric estimate does not depend on the stiffness, so it has nothing to choose.
        fit_options: ``loss``, ``loss_scale_mm`` of :func:`softgrip_calib.fit.fit`.

    Returns:
        The chosen model's fit (as :func:`softgrip_calib.fit.fit` returns it), whose
        ``fit.model_selection`` records every model tried: its held-out and fitted residual RMS
        (mm), or why it could not be judged, and the choice with its reason.

    Raises:
        FitError: as :func:`softgrip_calib.fit.fit` for the uniform model (no usable pair, no convergence,
            ...), or a non-mechanics estimator.
    """
    estimator = as_estimator(estimator)  # None: Mechanics()
    if estimator.name != "mechanics":
        raise FitError(f"the stiffness model only changes the mechanics estimate; the fit goes through the "
                       f"{estimator.name} estimate (fit it with softgrip_calib.fit.fit, or use Mechanics())")
    base = [p for p in dict.fromkeys(parameters) if p not in ("stiffness_ratio", "base_compliance")]
    options = dict(estimator=estimator, config=config, max_steps=max_steps, **fit_options)
    held_out = [i for i, obs in enumerate(observations) if not obs.free_closure]

    full: dict[str, tuple[CalibrationProfile, list]] = {}
    records: list[dict] = []
    previous = start
    for k, model in enumerate(STIFFNESS_MODELS):
        names = [*base, *model.parameters]
        record: dict[str, Any] = {"model": model.name, "parameters": list(model.parameters),
                                  "residual_rms_mm": None, "held_out_rms_mm": None, "failure": None}
        records.append(record)
        if k > 0 and len(held_out) < MIN_OBJECT_PAIRS:
            record["failure"] = (f"not tried: {len(held_out)} pair(s) with an object, and judging a model on a "
                                 f"held-out pair needs {MIN_OBJECT_PAIRS}")
            continue
        try:  # its warnings reach the user only if the model is chosen
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                profile = fit(observations, previous, names, skipped=skipped, progress=progress,
                              unconstrained="error" if k == 0 else "hold", **options)
        except FitError as err:
            if k == 0:
                raise
            record["failure"] = (f"did not converge: {err}" if isinstance(err, NotConvergedError) else str(err))
            continue
        full[model.name] = (profile, caught)
        record["residual_rms_mm"] = profile.fit.residual_rms_mm
        record["held_out_rms_mm"], why = _held_out_rms(observations, held_out, previous, names, options)
        if why is not None:
            record["failure"] = why
        previous = profile

    chosen, reason = _choose(records, len(held_out))
    profile, caught = full[chosen]
    for w in caught:
        warnings.warn(w.message, w.category, stacklevel=2)
    selection = {"chosen": chosen, "reason": reason, "candidates": records}
    return dataclasses.replace(profile, fit=dataclasses.replace(profile.fit, model_selection=selection))


def _held_out_rms(observations: Sequence[Observation], held_out: Sequence[int], start: CalibrationProfile,
                  names: Sequence[str], options: dict) -> tuple[float | None, str | None]:
    """Leave-one-pair-out RMS (mm) of the joint distances of the pairs ``held_out`` (indices), each
    predicted by the model ``names`` fitted to every other pair from ``start`` (the simpler model's
    fit to all pairs, where this model's fit to all pairs started); or (None, why) when a fold
    cannot be fitted or predicted, or with fewer than MIN_OBJECT_PAIRS pairs to leave out. A
    parameter the remaining pairs do not constrain (a finger that touches none of their objects)
    keeps its start value in that fold: the simpler model's, not a value the left-out pair shaped."""
    if len(held_out) < MIN_OBJECT_PAIRS:
        return None, None
    squares = []
    for i in held_out:
        train = [obs for j, obs in enumerate(observations) if j != i]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                profile = fit(train, start, names, progress=False, unconstrained="hold", **options)
        except FitError as err:
            return None, f"with {observations[i].label} left out: {err}"
        residuals, status = profile_residuals(profile, [observations[i]], estimator=options["estimator"],
                                              config=options["config"])
        if not (status == Status.OK).all():
            bad = ", ".join(Status(int(s)).name for s in status.ravel() if s != Status.OK)
            return None, f"{observations[i].label} left out: its estimate is invalid ({bad})"
        squares.append(np.mean(np.sum(residuals**2, axis=-1)))
    return float(np.sqrt(np.mean(squares))), None


def _choose(records: list[dict], object_pairs: int) -> tuple[str, str]:
    """The chosen model's name and why, from the records of :func:`fit_stiffness_model`."""
    uniform = records[0]
    if object_pairs < MIN_OBJECT_PAIRS:
        return uniform["model"], (
            f"{object_pairs} pair(s) with an object: the stiffness cannot be judged on a held-out pair from fewer "
            f"than {MIN_OBJECT_PAIRS}; kept the uniform finger. Add pairs whose object presses at different "
            f"heights along the fingers to let the fit decide")
    if uniform["held_out_rms_mm"] is None:
        return uniform["model"], (f"the uniform model could not be judged on held-out pairs ({uniform['failure']}); "
                                  f"kept it")
    chosen, steps = uniform, []
    for record in records[1:]:
        error = record["held_out_rms_mm"]
        if error is None:
            steps.append(f"{record['model']}: not judged ({record['failure']})")
            continue
        best = chosen["held_out_rms_mm"]
        needed = max(MIN_GAIN_MM, MIN_GAIN_FRACTION * best)
        if best - error >= needed:
            steps.append(f"{record['model']}: held out {error:.3f} mm against {best:.3f} mm, better by "
                         f"{best - error:.3f} mm (>= {needed:.3f}): chosen")
            chosen = record
        else:
            steps.append(f"{record['model']}: held out {error:.3f} mm against {best:.3f} mm, not better by "
                         f"{needed:.3f} mm or more: not needed")
    summary = f"uniform: held out {uniform['held_out_rms_mm']:.3f} mm; " + "; ".join(steps)
    failed = [r for r in records if r["failure"] is not None and r["held_out_rms_mm"] is None]
    if failed and chosen is not records[-1]:
        summary += (". A richer model could not be judged: add pairs (objects pressing near the fingers' bases "
                    "and near their tips) and fit again")
    return chosen["model"], summary


def describe_selection(selection: dict) -> list[str]:
    """Lines for a terminal: each model's held-out and fitted error, and the choice."""
    lines = []
    for record in selection["candidates"]:
        held = record["held_out_rms_mm"]
        fitted = record["residual_rms_mm"]
        mark = "*" if record["model"] == selection["chosen"] else " "
        text = (f"  {mark} {record['model']:<36} held out {'-' if held is None else f'{held:.3f} mm':>9}   "
                f"fitted {'-' if fitted is None else f'{fitted:.3f} mm':>9}")
        if record["failure"] is not None:
            text += f"   ({record['failure']})"
        lines.append(text)
    lines.append(f"  chosen: {selection['chosen']} ({selection['reason']})")
    return lines


__all__ = ["MIN_GAIN_FRACTION", "MIN_GAIN_MM", "MIN_OBJECT_PAIRS", "STIFFNESS_MODELS", "StiffnessModel",
           "describe_selection", "fit_stiffness_model"]
