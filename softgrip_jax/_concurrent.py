"""A batch split into parts that run side by side on a CPU's cores.

XLA:CPU runs the kernels of one computation one after another and spreads only the larger ones
over the cores: the estimate's many small kernels (gathers, the root finder's loop) leave the other
cores mostly idle (benchmarks/RESULTS.md, issue 2, measures what one computation gains from a
second core). Separate computations launched from separate threads do run side by side, so on a CPU the
batch functions split their candidates into one equal part per core, run the same compiled
function on each part from a thread, and concatenate the results on the device. Elsewhere (a GPU
fills itself with one computation), under tracing (``jit``, ``grad``, ``vmap`` of the batch
function) and for small batches, the function runs once on the whole batch. Every candidate is
computed independently, so the results agree either way to float32 rounding: a part and the whole
batch are programs of other shapes, and on some processors XLA:CPU vectorises the rows at a
chunk's edge differently (measured on an AMD EPYC: 3 of 7,700 coordinates differ, by 1.5e-7 of
their value; on the Intel Xeon of earlier runs, none).
"""

from __future__ import annotations

import numbers
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softgrip_base.errors import SoftgripError

#: Fewest candidates per part: below this a part's fixed costs outweigh the parallelism.
MIN_PART = 256

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()
_compiled: set = set()  # signatures already compiled: their first call runs alone (one compile)
_warm_lock = threading.Lock()
#: How long (s) :func:`_warm_threads` waits for all the pool's threads to be free before giving up.
_WARM_WAIT_S = 5.0


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def worker_count(workers: object) -> int:
    """Concurrent pieces at most: ``workers`` (checked here, as users pass it: an int >= 1 or None);
    None means one per core on a CPU backend and 1 on any other."""
    if workers is None:
        return available_cores() if jax.default_backend() == "cpu" else 1
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise SoftgripError(f"workers must be a positive integer (or None: one per CPU core), got {workers!r}")
    return workers


def part_count(workers: object, batch: int, operands=()) -> int:
    """How many concurrent parts a batch of ``batch`` candidates runs as (1: no split):
    :func:`worker_count`, but never more parts than ``batch / MIN_PART``; 1 if any leaf of
    ``operands`` is being traced."""
    workers = worker_count(workers)
    if is_traced(operands):
        return 1
    return max(1, min(workers, batch // MIN_PART))


def _executor(parts: int) -> ThreadPoolExecutor:
    """The shared thread pool, grown to at least ``parts`` threads."""
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < parts:
            # A smaller pool is left to itself, not shut down: another thread may still be
            # submitting parts to it.
            _pool, _pool_size = ThreadPoolExecutor(max_workers=parts, thread_name_prefix="softgrip-part"), parts
        return _pool


def is_traced(tree) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


def pad_rows(xs: jax.Array, rows: int) -> jax.Array:
    """``xs`` padded to ``rows`` rows with copies of its first row (zeros if it has none; results for
    them are dropped)."""
    pad = rows - xs.shape[0]
    if pad <= 0:
        return xs
    first = xs[:1] if xs.shape[0] else jnp.zeros((1,) + xs.shape[1:], xs.dtype)
    return jnp.concatenate([xs, jnp.broadcast_to(first, (pad,) + xs.shape[1:])])


#: A chunk of several is a multiple of this many rows: 8 solve groups of 16 float32 lanes (a chunk
#: of a size just short of such a multiple runs slower than the multiple).
CHUNK_ALIGN = 128


def balanced_chunk(rows: int, chunk_size: int) -> int:
    """The chunk size that scans ``rows`` rows in as few chunks of at most ``chunk_size`` rows as
    possible, all of one size (a multiple of :data:`CHUNK_ALIGN` when there are several), so that
    the last chunk is not mostly padding: 2,500 rows in chunks of at most 2048 are 2 chunks of 1280
    rows, not 2 of 2048 (4,096 rows computed).

    Example:
        >>> balanced_chunk(2500, 2048), balanced_chunk(1000, 2048), balanced_chunk(50_000, 2048)
        (1280, 1000, 2048)
    """
    if not isinstance(chunk_size, numbers.Integral) or isinstance(chunk_size, bool) or chunk_size < 1:
        raise SoftgripError(f"chunk_size must be a positive integer (candidates evaluated together; memory grows "
                            f"with it), got {chunk_size!r}")
    chunks = -(-rows // int(chunk_size))
    if chunks <= 1:
        return max(1, rows)
    even = -(-rows // chunks)
    return min(int(chunk_size), -(-even // CHUNK_ALIGN) * CHUNK_ALIGN)


#: The piece sizes a batch runs in when no ``chunk_size`` is given (:func:`bucket_piece`): each
#: compiled once, when a batch first needs it. Larger pieces cost less per candidate (fewer kernel
#: launches per candidate: benchmarks/RESULTS.md, "Piece sizes"); a piece of one lets a single
#: candidate cost one. Few sizes, since each is a compilation of seconds to tens of seconds.
PIECE_BUCKETS = (1, 256, 4096)

#: A piece's fixed cost in candidates' worth of work, as :func:`bucket_piece` weighs it by default:
#: a piece of one candidate takes about as long as this many candidates inside a large piece (an
#: SDF whose lookups cost more per candidate sets its own, ``AbstractSDF.piece_overhead``).
PIECE_OVERHEAD = 256


def bucket_piece(batch: int, workers: int, largest: int | None = None, overhead: int = PIECE_OVERHEAD) -> int:
    """The piece size of :data:`PIECE_BUCKETS` that runs ``batch`` candidates soonest on ``workers``
    concurrent workers, by the cost model ``rounds * (overhead + size)`` (``rounds``: pieces
    per worker, rounded up; ``overhead``: a piece's fixed cost in candidates); of equal costs the
    larger piece. ``largest``: no bucket above it (the smallest bucket if all are).

    Example:
        >>> [bucket_piece(b, 2) for b in (1, 2, 5, 605, 2_000, 10_000, 100_000)]
        [1, 1, 256, 256, 256, 4096, 4096]
        >>> [bucket_piece(b, 2, largest=256, overhead=16) for b in (5, 20, 40, 605)]  # PolygonSDF's settings
        [1, 1, 256, 256]
    """
    def cost(size: int) -> int:
        rounds = -(-max(1, -(-batch // size)) // max(1, workers))
        return rounds * (overhead + size)

    allowed = [size for size in PIECE_BUCKETS if largest is None or size <= largest] or [PIECE_BUCKETS[0]]
    return min(reversed(allowed), key=cost)


def piece_size(chunk_size: object, batch: int, workers: int) -> int:
    """``chunk_size`` checked (:func:`check_piece`), or for None the bucket :func:`bucket_piece`
    chooses for ``batch`` candidates on ``workers`` workers."""
    return bucket_piece(batch, workers) if chunk_size is None else check_piece(chunk_size)


def check_piece(chunk_size: object) -> int:
    """``chunk_size`` as a positive int, or a :class:`SoftgripError` naming it."""
    if not isinstance(chunk_size, numbers.Integral) or isinstance(chunk_size, bool) or chunk_size < 1:
        raise SoftgripError(f"chunk_size must be a positive integer (candidates evaluated together; memory grows "
                            f"with it), got {chunk_size!r}")
    return int(chunk_size)


def split_pieces(xs: jax.Array | np.ndarray, size: int) -> list:
    """``xs`` (B, ...) as ceil(B / size) pieces of exactly ``size`` rows (at least one), the last
    padded with copies of its first row (zeros for an empty batch). Split on the host with numpy:
    slicing a JAX array with Python integers compiles one small program per distinct bound, so a
    planner calling with ever new batch sizes would collect compiled programs (and memory maps)."""
    host = np.asarray(xs)
    b = host.shape[0]
    n = max(1, -(-b // size))
    pieces = [host[i * size:(i + 1) * size] for i in range(n)]
    last = pieces[-1]
    if last.shape[0] < size:
        fill = last[:1] if last.shape[0] else np.zeros((1,) + host.shape[1:], host.dtype)
        pieces[-1] = np.concatenate([last, np.broadcast_to(fill, (size - last.shape[0],) + host.shape[1:])])
    return pieces


#: Bytes of joined leaves sent to the device per ``jax.device_put`` call (:func:`join_pieces`).
_PUT_BYTES = 64 << 20


def join_pieces(outputs: list, b: int):
    """The pieces' outputs (pytrees of arrays with a leading axis ``size``) joined along it and cut to
    ``b`` rows. On a CPU backend the joining is numpy's, over zero-copy views, and the joined leaves
    go back to the device a group at a time (one ``jax.device_put`` per :data:`_PUT_BYTES` of them:
    one call per leaf would cost more than the joining for a batch of a few pieces; ``jnp.asarray``
    would compile a small program per shape): no program is compiled for a new B (XLA's
    ``concatenate`` and ``slice`` of new shapes would each compile one). Elsewhere it runs on the
    device. Each leaf's pieces are released once joined (the peak is the result plus a group)."""
    leaves = [jax.tree_util.tree_flatten(out)[0] for out in outputs]
    treedef = jax.tree_util.tree_structure(outputs[0])
    outputs.clear()
    if len(leaves) == 1 and all(leaf.shape[0] == b for leaf in leaves[0]):  # one piece, no padding: as it is
        return jax.tree_util.tree_unflatten(treedef, leaves[0])
    on_cpu = all(d.platform == "cpu" for leaf in leaves[0] for d in leaf.devices())
    joined: list[Any] = [None] * len(leaves[0])
    group: list[int] = []
    group_bytes = 0

    def put(group: list[int]) -> None:
        for k, array in zip(group, jax.device_put([joined[k] for k in group], may_alias=True)):
            joined[k] = array
        group.clear()

    for k in sorted(range(len(joined)), key=lambda k: -leaves[0][k].nbytes):
        parts = [part[k] for part in leaves]
        for part in leaves:
            part[k] = None
        if on_cpu:
            joined[k] = np.concatenate([np.asarray(x) for x in parts])[:b]
            group.append(k)
            group_bytes += joined[k].nbytes
            if group_bytes >= _PUT_BYTES:
                put(group)
                group_bytes = 0
        else:
            joined[k] = jnp.concatenate(parts)[:b]
        del parts
    if group:
        put(group)
    return jax.tree_util.tree_unflatten(treedef, joined)


def _warm_threads(pool: ThreadPoolExecutor, threads: int, task: Callable[[], object],
                  warm: frozenset[int] = frozenset()) -> None:
    """Run ``task`` once on each of ``threads`` distinct threads of ``pool`` but those already
    ``warm`` (thread idents): they wait for each other (at most :data:`_WARM_WAIT_S`) before running
    it, so no thread takes two; while other callers' pieces keep threads busy that long, none runs
    it. A program's first run on a thread costs tens of ms more than later ones
    (benchmarks/RESULTS.md): paid here, at the call that compiles, rather than by the first batch of
    several pieces."""
    if threads < 2:
        return
    barrier = threading.Barrier(threads, timeout=_WARM_WAIT_S)

    def on_a_thread_of_its_own() -> None:
        try:
            barrier.wait()
        except threading.BrokenBarrierError:  # threads busy with other callers' pieces: no warming
            return
        if threading.get_ident() in warm:
            return
        try:
            task()
        except Exception:  # noqa: BLE001 - only a head start: a piece that fails fails again when it runs
            pass

    with _warm_lock:  # two callers' warm-ups interleaved on the same threads would wait for each other
        for future in [pool.submit(on_a_thread_of_its_own) for _ in range(threads)]:
            future.result()


def run_in_pieces(fn, before: tuple, xs: jax.Array | np.ndarray, after: tuple, workers: int | None,
                  chunk_size: int | None,
                  progress: Callable[[int, int], None] | None = None, **static):
    """``fn(*before, piece, *after, chunk_size=..., **static)`` for a jitted ``fn`` whose outputs all
    have the candidates' leading axis, over pieces of exactly ``chunk_size`` candidates
    (:func:`split_pieces`; None: the :func:`bucket_piece` for the batch), as many in flight at once
    as there are workers, on the shared threads.

    Every batch size runs the compiled program of one of a few piece sizes: a planner that calls
    with thousands of different batch sizes compiles at most once per piece size, estimator and
    settings, and a batch costs its number of pieces.
    ``progress(done, total)`` is called on this thread after each piece, in order, ending with
    ``(B, B)``. Under tracing (``jit``, ``grad`` or ``vmap`` around the batch function) the traced
    batch is one program of its own shape, scanned in chunks of at most ``chunk_size``.
    """
    b = xs.shape[0]
    threads = worker_count(workers)
    size = piece_size(chunk_size, b, threads)
    if is_traced((before, xs, after)):
        return fn(*before, xs, *after, chunk_size=balanced_chunk(b, size), **static)
    pieces = split_pieces(xs, size)
    static = dict(static, chunk_size=size)
    leaves, treedef = jax.tree_util.tree_flatten((before, after))
    signature = (fn, treedef, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves),
                 pieces[0].shape, pieces[0].dtype, tuple(sorted(static.items())))

    ran_on: set[int] = set()  # the threads that ran this call's pieces

    def run(piece):
        ran_on.add(threading.get_ident())
        return jax.block_until_ready(fn(*before, jax.device_put(piece), *after, **static))

    pool = _executor(threads)  # the same pool every call: threads that have run the program before
    outputs: list = []

    def collect(output) -> None:
        outputs.append(output)
        if progress is not None:
            progress(min(b, len(outputs) * size), b)

    if signature not in _compiled:  # the first call compiles; the other pieces then reuse it
        collect(pool.submit(run, pieces[0]).result())
        if len(pieces) < threads:  # (with as many pieces as threads, each thread runs one now anyway)
            _warm_threads(pool, threads, lambda: run(pieces[0]), frozenset(ran_on))
        _compiled.add(signature)
    for future in [pool.submit(run, p) for p in pieces[len(outputs):]]:
        collect(future.result())
    return join_pieces(outputs, b)
