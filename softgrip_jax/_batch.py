"""Many candidates at once, in chunks so that memory stays bounded for any batch size.

Most of a finger's estimate is needed only where it touches the object: the root finder, the
contact chain and the second contact (and, with ``Mechanics()``, the equilibrium solve). Each
chunk therefore first brackets every finger's first contact (:func:`search_contact`; over the first
half of the sweep, then over the second half for only the fingers still free there), then refines
the contact only of the fingers whose bracket holds one (the others close freely, start in
collision, or are invalid: :func:`free_contact`), then hands the chunk's stages to the estimator's
``deform_batch`` (``Mechanics`` solves the equilibrium only of the fingers that touch). These steps
gather the needed candidates to the front and run them a group at a time
(:func:`~softgrip_jax._gather.where_needed`), so their cost follows the number of candidates that
need them rather than the batch size. The results are those of :func:`estimate`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from softgrip_jax._checks import check_finger, check_gripper, check_sdf
from softgrip_jax._compile import tuned_jit
from softgrip_jax._concurrent import bucket_piece, pad_rows, run_in_pieces, worker_count
from softgrip_jax._contact import ContactConfig, sweep_parts
from softgrip_jax._estimate import estimate_in_frame
from softgrip_jax._estimators import AbstractEstimator, as_estimator
from softgrip_jax._errors import SoftgripError
from softgrip_jax._export import exportable
from softgrip_jax._frames import FingerFrame
from softgrip_jax._grasp import GraspEstimate, finger_frames, per_finger
from softgrip_jax._gather import where_needed
from softgrip_jax._model import FingerModel, Gripper
from softgrip_jax._sdf import AbstractSDF
from softgrip_jax._sharding import device_mesh, run_sharded
from softgrip_jax._stage import (Estimate, finish_root_search, refine_search, search_contact, search_further,
                                start_root_search, stage_of)
from softgrip_jax._trace import trace_once

#: Chunks smaller than this refine every finger (see :func:`finger_chunk`).
_SMALL_CHUNK = 16

#: The fingers whose root finder has not converged with the others' are continued in groups of
#: this many (a few per chunk of thousands).
_LATE_GROUP = 32


def as_candidates(x, width: int, dtype, what: str, single: bool = False) -> jax.Array | np.ndarray:
    """``x`` as a (B, width) array of ``dtype`` (B may be 0), or a :class:`SoftgripError` saying what
    was expected: a batch of the wrong shape would otherwise be broadcast into wrong results or fail
    deep inside the computation. ``single``: a (width,) array is accepted too (and kept 1-D).

    A JAX array (or tracer) stays one; anything else becomes a numpy array on the host (``jnp.asarray``
    of a new shape would compile a small program per batch size)."""
    expected = f"{what} must be a (B, {width}) array of real numbers" + (f" or one ({width},)" if single else "")
    try:
        array = x if isinstance(x, jax.Array) else np.asarray(x)
    except (TypeError, ValueError) as err:
        raise SoftgripError(f"{expected}, got {type(x).__name__} that is not one ({err})") from None
    shape_ok = array.shape[-1:] == (width,) and (array.ndim == 2 or (single and array.ndim == 1))
    if not shape_ok or not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise SoftgripError(f"{expected}, got shape {array.shape} of {array.dtype}")
    return array if array.dtype == dtype else array.astype(dtype)


def geometric_stages(finger, sdf, frames, config, estimator):
    """:func:`geometric_stage` of a chunk of finger frames (leading axis), the contact refined
    (root finder, second contact) only for the fingers whose bracket holds a first contact."""
    first, second = sweep_parts(config) or (None, None)  # (None: the whole grid at once)
    searches = jax.vmap(lambda f: search_contact(finger, sdf, f, config, estimator, first))(frames)
    if second is not None:  # the grid's second part only for the fingers still free after its first
        free = ~searches.bracket.touches
        later = where_needed(lambda s: search_further(finger, sdf, s, config, second), free, searches)
        brackets = jax.tree_util.tree_map(lambda a, b: jnp.where(free, a, b), later, searches.bracket)
        searches = eqx.tree_at(lambda s: s.bracket, searches, brackets)
    need = jax.vmap(lambda s: s.need_refining)(searches)
    # The root finder's first iterations for every touching finger together, then the rest only
    # for the few not converged, in small groups, so that they do not hold up the others.
    roots = where_needed(lambda s: start_root_search(finger, sdf, s, config), need, searches)
    late = need & ~jax.vmap(lambda r: r.converged(config))(roots)
    later = where_needed(lambda sr: finish_root_search(finger, sdf, sr[0], config, sr[1]), late, (searches, roots),
                         group_size=_LATE_GROUP)
    roots = jax.tree_util.tree_map(lambda a, b: jnp.where(late, a, b), later, roots)
    refined = where_needed(lambda sr: refine_search(finger, sdf, sr[0], config, sr[1]), need, (searches, roots))
    return jax.vmap(lambda s, c: stage_of(finger, s, c))(searches, refined)


def finger_chunk(finger, sdf, frames, config, estimator):
    """Estimates of a chunk of finger frames (leading axis): the contact refined only where the
    finger touches the object, then the ``estimator``'s ``deform_batch`` (``Mechanics`` solves the
    equilibrium only where the finger touches).

    A chunk of 2 to ``_SMALL_CHUNK - 1`` fingers (a batch that small) is every finger's
    :func:`estimate_in_frame`, refined whether needed or not: sorting out the few that need it
    costs more there than it saves, in loops whose per-kernel cost sets a small batch's latency.
    """
    if 1 < frames.origin.shape[0] < _SMALL_CHUNK:  # (one finger: its refinement is one skippable group)
        return jax.vmap(lambda fr: estimate_in_frame(finger, sdf, fr, config, estimator=estimator))(frames)
    stages = geometric_stages(finger, sdf, frames, config, estimator)
    return estimator.deform_batch(finger, sdf, stages, config)


def map_chunks(fn, xs, chunk_size):
    """``fn`` on chunks of ``chunk_size`` rows of ``xs``, concatenated: outputs with ``xs``'s leading axis.

    Each chunk's output is written in place into the output arrays (a loop-carried buffer), so the
    function holds the result once, not once more for a stacked copy. The last chunk ends at the
    last row, overlapping the one before it instead of being padded (its overlapping rows are
    computed twice, to the same values: every row is independent). A batch of at most one chunk
    is padded with its first row.
    """
    b = xs.shape[0]
    if b <= chunk_size:  # no loop around one chunk (its per-iteration cost shows in a small batch's latency)
        return jax.tree_util.tree_map(lambda x: x[:b], fn(pad_rows(xs, chunk_size)))
    n_chunks = -(-b // chunk_size)
    starts = jnp.minimum(jnp.arange(n_chunks) * chunk_size, b - chunk_size)
    chunk = lambda start: jax.lax.dynamic_slice_in_dim(xs, start, chunk_size)  # noqa: E731
    shapes, fn = trace_once(fn, chunk(0))
    out = jax.tree_util.tree_map(lambda s: jnp.zeros((b,) + s.shape[1:], s.dtype), shapes)

    def write(i, out):
        start = starts[i]
        values = fn(chunk(start))
        return jax.tree_util.tree_map(lambda o, v: jax.lax.dynamic_update_slice_in_dim(o, v, start, 0), out, values)

    return jax.lax.fori_loop(0, n_chunks, write, out)


def run_batch(one_device, sharded, before: tuple, xs: jax.Array | np.ndarray, after: tuple, chunk_size: int | None,
              workers: int | None, estimator: AbstractEstimator, progress=None):
    """A jitted batch function over the candidates ``xs`` (B, ...), with outputs of leading axis B:
    with several JAX devices (GPUs, or processes joined by ``jax.distributed``) ``sharded`` on an
    even share per device (:func:`~softgrip_jax._sharding.run_sharded`), else ``one_device`` in
    pieces of ``chunk_size`` candidates (None: a bucketed size chosen by B, at most the SDF's
    ``largest_piece``; ``before`` is ``(finger or gripper, sdf)``), ``workers`` at a time
    (:func:`~softgrip_jax._concurrent.run_in_pieces`): one compiled program per piece size. Both
    are called as ``fn(*before, xs, *after, chunk_size=...,
    estimator=estimator)``; ``progress(done, total)`` after each piece."""
    mesh = device_mesh()
    if chunk_size is None:  # the piece size for this batch, no larger than the object's lookups allow
        parallel = mesh.devices.size if mesh is not None else worker_count(workers)
        chunk_size = bucket_piece(xs.shape[0], parallel, largest=before[1].largest_piece,
                                  overhead=before[1].piece_overhead)
    if mesh is not None:
        return run_sharded(sharded, mesh, before, xs, after, chunk_size, progress, estimator=estimator)
    return run_in_pieces(one_device, before, xs, after, workers, chunk_size, progress, estimator=estimator)


def _estimate_share(finger, sdf, bases, config, chunk_size, estimator):
    frames = jax.vmap(FingerFrame.hanging_from)
    return map_chunks(lambda chunk: finger_chunk(finger, sdf, frames(chunk), config, estimator), bases, chunk_size)


#: Static arguments of the jitted batch functions: the estimator is keyed by value (its class and settings).
_STATIC = ("chunk_size", "estimator")

_estimate_batch = exportable(tuned_jit(_estimate_share, static_argnames=_STATIC), _STATIC)


@partial(tuned_jit, static_argnames=_STATIC)
def _estimate_sharded(finger, sdf, bases, config, chunk_size, estimator):
    # bases: (devices, per_device, 2); the device axis is vmapped (and sharded across the devices).
    return jax.vmap(lambda share: _estimate_share(finger, sdf, share, config, chunk_size, estimator))(bases)


def grasp_chunk(gripper, sdf, poses, config, estimator):
    left, right = jax.vmap(lambda p: finger_frames(gripper, p))(poses)
    left, right = per_finger(lambda finger, frames: finger_chunk(finger, sdf, frames, config, estimator),
                             gripper, (left, right), in_turn=True)
    return jax.vmap(lambda a, b: GraspEstimate(left=a, right=b, valid=a.valid & b.valid))(left, right)


def _estimate_grasp_share(gripper, sdf, poses, config, chunk_size, estimator):
    return map_chunks(lambda chunk: grasp_chunk(gripper, sdf, chunk, config, estimator), poses, chunk_size)


_estimate_grasp_batch = exportable(tuned_jit(_estimate_grasp_share, static_argnames=_STATIC), _STATIC)


@partial(tuned_jit, static_argnames=_STATIC)
def _estimate_grasp_sharded(gripper, sdf, poses, config, chunk_size, estimator):
    return jax.vmap(lambda share: _estimate_grasp_share(gripper, sdf, share, config, chunk_size, estimator))(poses)


def estimate_batch(
    finger: FingerModel,
    sdf: AbstractSDF,
    bases: Float[ArrayLike, "b 2"],
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int | None = None,
    estimator: AbstractEstimator | None = None,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Estimate:
    """:func:`estimate` for B finger bases (mm), compiled once per shape, ``chunk_size`` at a time.

    Returns an :class:`Estimate` whose every leaf has a leading axis of length B. A bad base
    (NaN, outside the SDF grid) comes back ``valid=False`` and does not affect the others.
    ``estimator`` is as for :func:`estimate`; with
    ``Mechanics()`` (the default) the equilibrium is solved only for the candidates that touch the object. With several JAX devices
    (GPUs, or processes joined by ``jax.distributed``) the batch is split evenly across them, as
    :func:`~softgrip_jax.score` does (:mod:`softgrip_jax._sharding`); results are one device's.

    Args:
        bases: (B, 2) finger bases in mm (each finger hangs toward +y and curls toward +x).
        chunk_size: bases per compiled call (a piece; static); memory grows with it, not with B.
            None (default): a piece size of :data:`~softgrip_jax._concurrent.PIECE_BUCKETS`
            chosen by B (one base runs as a piece of one, 100,000 as pieces of 4096), each
            compiled once, when first needed. An int: every B runs through the program of that size.
        estimator: ``Geometric()`` or ``Mechanics(config)`` (None: ``Mechanics()``); equal
            estimators reuse one compiled program.
        workers: on one device, pieces run at once (None: one per CPU core on a CPU backend, one
            elsewhere; see :mod:`softgrip_jax._concurrent`). Results are the same whatever it is.
        progress: called as ``progress(done, total)`` (candidates) after each piece, on the
            calling thread, ending with ``(B, B)``; e.g. a tqdm bar's update, or a planner's
            deadline check (raising from it stops the batch).

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Geometric, PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> bases = jnp.array([[0.0, 0.0], [-60.0, 0.0], [jnp.nan, 0.0]])  # mm
        >>> est = estimate_batch(f, PolygonSDF.regular((20.0, 30.0), 8.0), bases, estimator=Geometric())
        >>> est.joints.shape, est.case_name[:2].tolist(), est.valid.tolist()
        ((3, 11, 2), ['other', 'none'], [True, True, False])
    """
    check_finger(finger)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    bases = as_candidates(bases, 2, finger.length.dtype, "estimate_batch: bases")
    return run_batch(_estimate_batch, _estimate_sharded, (finger, sdf), bases, (config,), chunk_size, workers, estimator,
                     progress)


def estimate_grasp_batch(
    gripper: Gripper,
    sdf: AbstractSDF,
    poses: Float[ArrayLike, "b 3"],
    config: ContactConfig = ContactConfig(),
    *,
    chunk_size: int | None = None,
    estimator: AbstractEstimator | None = None,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> GraspEstimate:
    """:func:`estimate_grasp` for B poses (x mm, y mm, angle rad), ``chunk_size`` at a time.

    ``estimator`` is as for :func:`estimate_grasp`.

    Args:
        poses: (B, 3) gripper poses: centre x, y (mm) and angle (rad).
        workers: as for :func:`estimate_batch`.
        progress: as for :func:`estimate_batch`.

    Returns:
        :class:`GraspEstimate` with leading axis B: ``left`` and ``right`` :class:`Estimate` s
        (joints (B, N+1, 2) mm) and ``valid`` (B,).

    Example:
        >>> import jax.numpy as jnp
        >>> from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF
        >>> f = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=10)
        >>> poses = jnp.array([[0.0, 0.0, 0.0], [0.0, -100.0, 0.0]])  # mm, mm, rad
        >>> g = estimate_grasp_batch(Gripper(f, f, 50.0), PolygonSDF.regular((0.0, 35.0), 9.0), poses,
        ...                          estimator=Geometric())
        >>> g.left.joints.shape, g.valid.tolist()
        ((2, 11, 2), [True, True])
    """
    check_gripper(gripper)
    check_sdf(sdf)
    estimator = as_estimator(estimator)
    poses = as_candidates(poses, 3, gripper.base_separation.dtype, "estimate_grasp_batch: poses")
    return run_batch(_estimate_grasp_batch, _estimate_grasp_sharded, (gripper, sdf), poses, (config,), chunk_size,
                     workers, estimator, progress)
