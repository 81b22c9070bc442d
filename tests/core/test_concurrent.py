"""Batches run as pieces of one size (softgrip_jax._concurrent): the same results whatever the batch
size or the number of workers, one compiled program for every batch size, progress after each piece."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softgrip_jax import FingerModel, Gripper, PolygonSDF, SDFGrid, SoftgripError, estimate_batch, score
from softgrip_jax._concurrent import CHUNK_ALIGN, MIN_PART, balanced_chunk, part_count, run_in_pieces
from softgrip_jax import Geometric

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=4)
GRID = SDFGrid.sample(PolygonSDF.regular((30.0, 40.0), 8.0, 64), origin=(-40.0, -30.0), spacing=(0.5, 0.5),
                      shape=(200, 240))


CHUNK = 128  # small pieces keep the tests fast


@pytest.fixture(scope="module")
def bases():
    return np.random.default_rng(0).uniform([-20.0, -10.0], [40.0, 30.0], (3 * CHUNK + 2, 2)).astype(np.float32)


@pytest.fixture(scope="module")
def whole(bases):
    return estimate_batch(FINGER, GRID, bases, estimator=Geometric(), workers=1, chunk_size=CHUNK)


def test_pieces_give_the_whole_batch_results_in_order(bases, whole):
    # 4 pieces of 128 rows, the last padded by 126, run 3 at a time: every row is computed by the
    # same program in every case, so the results are bitwise those of one worker.
    split = estimate_batch(FINGER, GRID, bases, estimator=Geometric(), workers=3, chunk_size=CHUNK)
    assert split.joints.shape == (len(bases), 5, 2)
    np.testing.assert_array_equal(split.joints, whole.joints)
    np.testing.assert_array_equal(split.case, whole.case)
    assert len(set(np.asarray(whole.case).tolist())) >= 3  # a scene with contacts, not only case (a)


@pytest.mark.parametrize("size", [1, 7, CHUNK, CHUNK + 1, 300])
def test_a_row_is_the_same_in_every_batch_size(bases, whole, size):
    part = estimate_batch(FINGER, GRID, bases[:size], estimator=Geometric(), chunk_size=CHUNK)
    assert part.joints.shape == (size, 5, 2)
    np.testing.assert_array_equal(part.joints, whole.joints[:size])
    np.testing.assert_array_equal(part.valid, whole.valid[:size])


def test_new_batch_sizes_compile_nothing_and_map_no_memory(bases, whole):
    def maps():
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)

    estimate_batch(FINGER, GRID, bases[:5], estimator=Geometric(), chunk_size=CHUNK)  # warm: every helper compiled
    before, compiled = maps(), []
    with jax.log_compiles(True):
        import logging

        class Catch(logging.Handler):
            def emit(self, record):
                compiled.append(record.getMessage())

        handler = Catch()
        logging.getLogger("jax").addHandler(handler)
        try:
            for size in np.random.default_rng(1).integers(1, len(bases), 40):
                estimate_batch(FINGER, GRID, bases[:size], estimator=Geometric(), chunk_size=CHUNK)
        finally:
            logging.getLogger("jax").removeHandler(handler)
    assert [m for m in compiled if "Compiling" in m or "compil" in m.lower()] == []
    assert maps() - before < 20  # (allocator growth, not a program per size)


def test_progress_is_reported_after_each_piece_ending_with_the_whole_batch(bases, whole):
    calls = []
    estimate_batch(FINGER, GRID, bases[:300], estimator=Geometric(), chunk_size=CHUNK, workers=2,
                   progress=lambda done, total: calls.append((done, total)))
    assert calls == [(128, 300), (256, 300), (300, 300)]


def test_part_count_rules():
    assert part_count(4, 10 * MIN_PART) == 4
    assert part_count(4, 2 * MIN_PART + 1) == 2  # never a part below MIN_PART candidates
    assert part_count(4, MIN_PART - 1) == 1 and part_count(4, 0) == 1
    assert 1 <= part_count(None, 100 * MIN_PART)
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(SoftgripError, match="workers must be a positive integer"):
            part_count(bad, 1000)


def test_chunks_are_equal_and_never_above_chunk_size():
    # As few chunks as chunk_size allows, all of one size: the last is not mostly padding.
    for rows in (1, 7, 2048, 2049, 2500, 50_000, 99_999):
        for chunk in (1, 100, 2048, 4096):
            size = balanced_chunk(rows, chunk)
            count = -(-rows // size)
            assert size <= chunk and count == -(-rows // chunk)
            if count == 1:
                assert size == rows
            elif size < chunk:
                assert size % CHUNK_ALIGN == 0 and count * size - rows < count * CHUNK_ALIGN
    assert balanced_chunk(2049, 2048) == 1152  # 2 chunks of 1152, not 2 of 2048
    for bad in (0, -1, True):  # (the tests check type hints too: a float would not get this far)
        with pytest.raises(SoftgripError, match="chunk_size must be a positive integer"):
            estimate_batch(FINGER, GRID, np.zeros((3, 2), np.float32), chunk_size=bad, estimator=Geometric())


@pytest.mark.slow  # compiles a gradient through a batch: about 35 s
def test_traced_batches_run_as_one_part():
    # Under jit or grad the inputs are tracers: one part, and the gradient still flows.
    assert jax.jit(lambda x: part_count(4, 10 * MIN_PART, (x,)))(jnp.zeros(1)) == 1
    bases = jnp.asarray(np.random.default_rng(2).uniform([-20.0, -10.0], [10.0, 30.0], (2 * MIN_PART, 2)),
                        jnp.float32)

    def loss(theta):
        f = FingerModel(length=50.0, theta_entire=theta, half_thickness=3.0, n_links=4)
        return jnp.sum(estimate_batch(f, GRID, bases, estimator=Geometric(), workers=2).joints[:, -1, 0])

    assert np.isfinite(jax.grad(loss)(jnp.float32(0.5)))


def test_every_batch_size_traces_one_piece_program():
    traces = []

    @functools.partial(jax.jit, static_argnames="chunk_size")
    def double(x, chunk_size):
        traces.append(x.shape)  # runs only while tracing
        return {"twice": 2.0 * x}

    for rows in (1, 100, 256, 257, 1000):
        xs = jnp.arange(rows * 2, dtype=jnp.float32).reshape(-1, 2)
        out = run_in_pieces(double, (), xs, (), 4, 256)
        np.testing.assert_array_equal(out["twice"], 2.0 * xs)
    assert traces == [(256, 2)]


@pytest.mark.slow  # compiles the score: about 50 s
def test_score_in_parts_matches_one_part():
    n = 2 * MIN_PART + 1
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(0.0, 60.0, n), rng.uniform(-10.0, 10.0, n),
                             rng.uniform(-0.2, 0.2, n)]).astype(np.float32)
    gripper = Gripper(FINGER, FINGER, 50.0)
    whole = score(gripper, GRID, poses, estimator=Geometric(), workers=1)
    split = score(gripper, GRID, poses, estimator=Geometric(), workers=2)
    np.testing.assert_array_equal(split.score, whole.score)  # the same piece program for every row
    np.testing.assert_array_equal(split.valid, whole.valid)
    assert np.isfinite(np.asarray(whole.score)).sum() > 10  # some poses are valid, so scores were compared


@pytest.mark.parametrize("put_bytes", [1, 64 << 20], ids=["a device_put per leaf", "one device_put"])
def test_join_pieces_joins_each_leaf_in_order_and_cuts_the_padding(monkeypatch, put_bytes):
    import softgrip_jax._concurrent as concurrent

    monkeypatch.setattr(concurrent, "_PUT_BYTES", put_bytes)
    rows = np.arange(7 * 3 * 2, dtype=np.float32).reshape(7, 3, 2)
    flags = np.arange(7) % 3 == 0
    pieces = [{"rows": jnp.asarray(rows[i:i + 3]), "flags": jnp.asarray(flags[i:i + 3]),
               "codes": jnp.arange(i, i + 3, dtype=jnp.int32)} for i in (0, 3, 6)]
    pieces[-1] = jax.tree_util.tree_map(lambda x: jnp.concatenate([x[:1]] * 3), pieces[-1])  # 1 row + padding
    joined = concurrent.join_pieces(pieces, 7)
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree_util.tree_leaves(joined))
    np.testing.assert_array_equal(np.asarray(joined["rows"]), rows)
    np.testing.assert_array_equal(np.asarray(joined["flags"]), flags)
    assert joined["codes"].dtype == jnp.int32 and np.asarray(joined["codes"]).tolist() == [0, 1, 2, 3, 4, 5, 6]


def test_one_unpadded_piece_is_returned_as_it_is_and_a_padded_one_is_cut():
    import softgrip_jax._concurrent as concurrent

    piece = {"rows": jnp.arange(6.0).reshape(3, 2), "codes": jnp.arange(3, dtype=jnp.int32)}
    whole = concurrent.join_pieces([dict(piece)], 3)
    assert whole["rows"] is piece["rows"] and whole["codes"] is piece["codes"]  # no copy, no device_put
    cut = concurrent.join_pieces([dict(piece)], 2)
    np.testing.assert_array_equal(np.asarray(cut["rows"]), [[0.0, 1.0], [2.0, 3.0]])
    assert np.asarray(cut["codes"]).tolist() == [0, 1]


def test_warm_threads_runs_the_task_once_on_each_thread_even_with_two_callers_at_once():
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from softgrip_jax._concurrent import _warm_threads

    pool = ThreadPoolExecutor(max_workers=3)
    seen: list[int] = []
    lock = threading.Lock()

    def task():
        with lock:
            seen.append(threading.get_ident())

    _warm_threads(pool, 3, task)
    assert len(seen) == 3 and len(set(seen)) == 3  # three distinct threads, once each
    first = seen[0]
    seen.clear()
    _warm_threads(pool, 3, task, frozenset({first}))  # a thread already warm is left out
    assert len(seen) == 2 and first not in seen
    seen.clear()
    callers = [threading.Thread(target=_warm_threads, args=(pool, 3, task)) for _ in range(2)]
    for caller in callers:
        caller.start()
    for caller in callers:
        caller.join(timeout=30)
    assert not any(c.is_alive() for c in callers)  # no deadlock between the two warm-ups
    assert len(seen) == 6 and len(set(seen)) == 3
    pool.shutdown()


def test_warm_threads_gives_up_when_a_thread_stays_busy(monkeypatch):
    import threading
    from concurrent.futures import ThreadPoolExecutor

    import softgrip_jax._concurrent as concurrent

    monkeypatch.setattr(concurrent, "_WARM_WAIT_S", 0.2)
    pool = ThreadPoolExecutor(max_workers=2)
    release = threading.Event()
    busy = pool.submit(release.wait, 30)  # another caller's long piece holds one thread
    ran: list[int] = []
    warming = threading.Thread(target=concurrent._warm_threads, args=(pool, 2, lambda: ran.append(1)))
    warming.start()
    warming.join(timeout=10)
    # The warm-up gave up after the barrier's timeout, while the other caller's piece still runs:
    # no task ran (a lone thread is not warmed twice), and nobody waited for the busy thread.
    assert not warming.is_alive() and not busy.done()
    assert ran == []
    release.set()
    busy.result()
    pool.shutdown()


def test_a_warm_up_that_fails_does_not_fail_the_call():
    from concurrent.futures import ThreadPoolExecutor

    from softgrip_jax._concurrent import _warm_threads

    pool = ThreadPoolExecutor(max_workers=2)
    _warm_threads(pool, 2, lambda: 1 / 0)  # e.g. memory for two pieces at once: the batch's own run decides
    assert pool.submit(lambda: 7).result() == 7  # the pool still serves
    pool.shutdown()


def test_a_default_batch_runs_in_the_piece_size_its_size_needs():
    from softgrip_jax._concurrent import PIECE_BUCKETS, bucket_piece

    for workers in (1, 2, 4):
        sizes = [bucket_piece(b, workers) for b in range(1, 20_000, 7)]
        assert set(sizes) <= set(PIECE_BUCKETS)
        assert sizes == sorted(sizes)  # a larger batch never gets a smaller piece
    assert bucket_piece(1, 2) == 1  # one pose costs a piece of one, not of hundreds
    assert bucket_piece(100_000, 2) == max(PIECE_BUCKETS)
    # Against a polygon whose every lookup reads every edge, a few poses run as pieces of one: a
    # piece of 256 would cost about 256 poses' lookups. With its edges indexed by cells it runs as
    # a grid does.
    from softgrip_jax import PolygonSDF

    disc = PolygonSDF.regular((0.0, 38.0), 15.0, 128)
    every_edge = PolygonSDF(disc.vertices, edge_cells=False)
    polygon = dict(largest=every_edge.largest_piece, overhead=every_edge.piece_overhead)
    assert [bucket_piece(b, 2, **polygon) for b in (5, 20)] == [1, 1]
    assert bucket_piece(605, 2, **polygon) == 256
    assert (disc.largest_piece, disc.piece_overhead) == (4096, 256)
    # Padding stays bounded: a batch computes at most twice its rows, or a piece per worker.
    for b in range(1, 20_000, 13):
        size = bucket_piece(b, 2)
        assert -(-b // size) * size <= max(2 * b, 2 * size)


def test_the_default_pieces_give_the_fixed_pieces_results():
    bases = np.random.default_rng(5).uniform(-20.0, 10.0, (70, 2)).astype(np.float32)
    default = estimate_batch(FINGER, GRID, bases, estimator=Geometric())  # a piece of 256
    fixed = estimate_batch(FINGER, GRID, bases, estimator=Geometric(), chunk_size=CHUNK)
    np.testing.assert_array_equal(default.case, fixed.case)
    np.testing.assert_array_equal(default.valid, fixed.valid)
    np.testing.assert_allclose(default.joints, fixed.joints, atol=1e-4)
