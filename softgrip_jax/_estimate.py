"""The whole estimate of one finger: its contact prediction (eqs. 5-8, eq. 9's case), then the
deformation its estimator gives (:mod:`softgrip_jax._estimators`).

Batched versions are :mod:`softgrip_jax._batch`; both fingers of a gripper, :mod:`softgrip_jax._grasp`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from softgrip_jax._contact import ContactConfig
from softgrip_jax._estimators import AbstractEstimator, as_estimator
from softgrip_jax._frames import FingerFrame
from softgrip_jax._checks import check_finger, check_sdf
from softgrip_jax._model import FingerModel
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._stage import Estimate, geometric_stage


def estimate_in_frame(
    finger: FingerModel,
    sdf: AbstractSDF,
    frame: FingerFrame,
    config: ContactConfig = ContactConfig(),
    *,
    estimator: AbstractEstimator | None = None,
) -> Estimate:
    """Estimate one finger placed by ``frame`` (base, gripper angle, handedness); image-plane output.

    ``estimator`` chooses the deformation: ``Mechanics()`` (None: the default; the spring chain at
    equilibrium, :mod:`softgrip_jax._mechanics`, solved with ``Mechanics(config)``'s settings
    wherever the finger touches the object) or ``Geometric()`` (the paper's eq. 9); a name such
    as ``"geometric"`` becomes one with :func:`~softgrip_jax.as_estimator`.

    Example (a right finger, mirrored: it curls toward -x):
        >>> import jax, jax.numpy as jnp
        >>> from softgrip_jax import Geometric, PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> frame = FingerFrame(origin=jnp.zeros(2), angle=jnp.array(0.0), handedness=jnp.array(-1.0))
        >>> run = jax.jit(estimate_in_frame)  # compiles once per estimator; op by op is slower
        >>> est = run(f, PolygonSDF.regular((100.0, 30.0), 5.0), frame, estimator=Geometric())
        >>> bool(est.joints[-1, 0] < 0), est.joints.shape  # tip left of the base; (N+1, 2) mm
        (True, (11, 2))
    """
    check_finger(finger)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    stage = geometric_stage(finger, sdf, frame, config, estimator)
    return estimator.deform(finger, sdf, stage, config)


def estimate(
    finger: FingerModel,
    sdf: AbstractSDF,
    base: Float[ArrayLike, "2"],
    config: ContactConfig = ContactConfig(),
    *,
    estimator: AbstractEstimator | None = None,
) -> Estimate:
    """Estimate the deformation of a finger hanging from ``base`` (mm) and curling toward +x.

    The whole pipeline for one finger: contact prediction (eqs. 5-8), then the deformation chosen by
    ``estimator``: ``Mechanics(config)`` (None: the default, ``Mechanics()``), the spring chain at
    equilibrium against the object (:mod:`softgrip_jax._mechanics`), or ``Geometric()``, the
    paper's deformation of the predicted case (eq. 9). Pure and jit-, vmap- and grad-compatible (an
    estimator has no array leaves: under ``jax.jit`` it is part of the compiled signature); a NaN or
    out-of-grid ``base`` gives ``valid=False`` and NaN joints without affecting other batch elements.

    Example:
        >>> import jax, jax.numpy as jnp
        >>> from softgrip_jax import Geometric, PolygonSDF
        >>> finger = FingerModel(length=50.0, theta_entire=0.4, half_thickness=3.0, n_links=10)
        >>> run = jax.jit(estimate)  # compiles once per estimator; op by op is slower
        >>> est = run(finger, PolygonSDF.regular((60.0, 40.0), 8.0), jnp.zeros(2), estimator=Geometric())
        >>> est.case_name, est.joints.shape  # joints: (N+1, 2) mm, base first
        ('none', (11, 2))
    """
    check_finger(finger)
    check_sdf(sdf)
    frame = FingerFrame.hanging_from(jnp.asarray(base, finger.length.dtype))
    return estimate_in_frame(finger, sdf, frame, config, estimator=estimator)
