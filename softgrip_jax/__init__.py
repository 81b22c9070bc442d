"""softgrip-jax: pre-touch deformation estimation of a soft gripper, as a differentiable JAX core.

Where each equation of the paper lives:

====================  ===============================================================
eqs. 1-3              :mod:`softgrip_jax._kinematics` (``forward_kinematics``, ``chain_points``,
                      ``pcc_turning``, ``pcc_joints``; eq. 2 in closed form ``pcc_chord_joints``)
eqs. 5-8, Figs. 7-8   :mod:`softgrip_jax._contact` (``predict_contact``)
eq. 9, Figs. 9-11     :mod:`softgrip_jax._deformation` (``case_shapes``)
spring chain [16]     :mod:`softgrip_jax._mechanics` (``Mechanics(MechanicsConfig(...))``)
eq. 10                :mod:`softgrip_jax._metrics` (``joint_errors``)
grasp quality         :mod:`softgrip_jax._quality` (friction-cone wrenches, Ferrari-Canny L1 epsilon),
                      :mod:`softgrip_jax._robust` (``Uncertainty``: expected quality, P(closure))
====================  ===============================================================

One finger's estimate runs these in stages (:mod:`softgrip_jax._stage`: inputs checked, contact,
eq. 9's shape, the estimator, ``finish``); :mod:`softgrip_jax._batch` runs the stages for many
candidates and holds no equation.

The deformation estimate is an object (:mod:`softgrip_jax._estimators`), passed as ``estimator=`` to
every estimate, score and refine function: ``Geometric()`` (the paper's eq. 9) or
``Mechanics(config)`` (the default), the spring chain at equilibrium (the paper's ref. [16]), which
is beyond the paper. New estimators subclass ``AbstractEstimator``.

The object is a signed-distance function (:mod:`softgrip_jax._sdf`); fingers at other places,
rotated or mirrored, see it through a frame (:mod:`softgrip_jax._frames`). The layers, conventions,
frames and units and the estimators' assumptions are described in the source tree's ``docs/design.md``.
"""

from softgrip_jax._cache import CacheWarning, UntrustedCacheWarning, enable_compilation_cache
from softgrip_jax._batch import estimate_batch, estimate_grasp_batch
from softgrip_jax._contact import CASE_NAMES, Contact, ContactCase, ContactConfig, predict_contact, predict_contact_local, sweep_shape
from softgrip_jax._deformation import case_shapes
from softgrip_jax._estimate import estimate, estimate_in_frame
from softgrip_jax._estimators import DEFAULT_ESTIMATOR, AbstractEstimator, Geometric, Mechanics, as_estimator
from softgrip_base.errors import SoftgripError
from softgrip_jax._frames import FingerFrame
from softgrip_jax._grasp import GraspEstimate, estimate_grasp, finger_frames
from softgrip_jax._kinematics import chain_points, chain_stations, forward_kinematics, link_angles, pcc_joints, pcc_turning
from softgrip_jax._mechanics import DEFAULT_METHOD, METHODS, MechanicsConfig, link_stiffness
from softgrip_jax._metrics import joint_errors
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._names import code_names
from softgrip_jax._quality import DEFAULT_MU, FingerContacts, edge_wrenches, epsilon_l1
from softgrip_jax._robust import Uncertainty
from softgrip_jax._score import (RefineStatus, Refined, Score, ScoreComponents, ScoreWeights, refine, score,
                                 score_pose)
from softgrip_jax._sdf import FAR_MM, AbstractSDF, PolygonSDF, SDFGrid
from softgrip_jax._stage import Estimate, Status

__all__ = [
    "AbstractEstimator", "AbstractSDF", "CASE_NAMES", "DEFAULT_ESTIMATOR", "Geometric", "Mechanics", "as_estimator", "FAR_MM", "Contact", "ContactCase", "ContactConfig", "Estimate", "FingerFrame",
    "FingerModel", "GraspEstimate", "Gripper", "PolygonSDF", "SDFGrid", "SoftgripError",
    "Status", "case_shapes", "code_names", "chain_points", "chain_stations", "estimate", "estimate_batch", "estimate_grasp",
    "enable_compilation_cache", "estimate_grasp_batch", "estimate_in_frame", "finger_frames", "forward_kinematics",
    "joint_errors", "link_angles", "link_stiffness", "DEFAULT_METHOD", "METHODS", "MechanicsConfig", "RefineStatus", "Refined", "Score", "ScoreComponents", "ScoreWeights",
    "refine", "score", "CacheWarning", "UntrustedCacheWarning", "DEFAULT_MU", "FingerContacts", "edge_wrenches",
    "epsilon_l1", "Uncertainty", "score_pose", "pcc_joints", "pcc_turning", "predict_contact", "predict_contact_local", "sweep_shape",
]
