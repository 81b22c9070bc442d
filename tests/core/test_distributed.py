"""The batch functions across several processes (``jax.distributed``) and several local devices.

Two processes on this machine join over loopback with CPU collectives (gloo), each holding one CPU
device; ``estimate_batch`` and ``score`` split one batch across the two and every process gets
the whole result, equal to one process's.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from softgrip_jax import FingerModel, Gripper, PolygonSDF, estimate_batch, score
from softgrip_jax import Geometric

FINGER = FingerModel(length=50.0, theta_entire=0.5, half_thickness=3.0, n_links=8)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=50.0)
DISC = PolygonSDF.regular((0.0, 35.0), 9.0, 64)
# Odd sizes: the shares are padded to equal lengths, and the padding must not show.
BASES = np.array([[-12.0, 0.0], [-8.0, 2.0], [-4.0, 0.0], [0.0, -3.0], [-60.0, 0.0]], np.float32)
POSES = np.array([[0.0, 0.0, 0.0], [2.0, -3.0, 0.1], [0.0, -100.0, 0.0]], np.float32)

WORKER = textwrap.dedent("""
    import sys
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    port, rank, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=rank)
    import numpy as np
    from tests.core.test_distributed import BASES, DISC, FINGER, GRIPPER, POSES
    from softgrip_jax import Geometric, estimate_batch, score
    assert jax.process_count() == 2 and len(jax.devices()) == 2 and len(jax.local_devices()) == 1, jax.devices()
    steps = []
    est = estimate_batch(FINGER, DISC, BASES, estimator=Geometric(), chunk_size=4, progress=lambda d, n: steps.append(d))
    sc = score(GRIPPER, DISC, POSES, estimator=Geometric(), chunk_size=4)
    n = len(BASES)
    assert steps == [min(8 * k, n) for k in range(1, -(-n // 8) + 1)], steps  # rounds of a 4-base piece per device
    np.savez(out, joints=np.asarray(est.joints), case=np.asarray(est.case), valid=np.asarray(est.valid),
             score=np.asarray(sc.score), score_valid=np.asarray(sc.valid), left=np.asarray(sc.grasp.left.joints))
    jax.distributed.shutdown()
    print("OK", rank)
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _check(got, est, sc=None):
    np.testing.assert_array_equal(got["valid"], np.asarray(est.valid))
    np.testing.assert_array_equal(got["case"], np.asarray(est.case))
    np.testing.assert_allclose(got["joints"], np.asarray(est.joints), atol=1e-4)
    if sc is None:
        return
    np.testing.assert_array_equal(got["score_valid"], np.asarray(sc.valid))
    np.testing.assert_allclose(got["score"], np.asarray(sc.score), atol=1e-5)
    np.testing.assert_allclose(got["left"], np.asarray(sc.grasp.left.joints), atol=1e-4)


@pytest.fixture(scope="module")
def one_process():
    """The batch's results in this (one-device) process; a mix of valid, invalid, touching and free."""
    est = estimate_batch(FINGER, DISC, BASES, estimator=Geometric(), chunk_size=4)
    sc = score(GRIPPER, DISC, POSES, estimator=Geometric(), chunk_size=4)
    valid, case = np.asarray(est.valid), np.asarray(est.case)
    assert valid.any() and not valid.all() and (case[valid] != 0).any() and (case[valid] == 0).any()
    assert np.asarray(sc.valid)[:2].all() and np.asarray(sc.score)[1] != np.asarray(sc.score)[0]
    return est, sc


@pytest.mark.slow
def test_two_processes_give_one_process_result(tmp_path, one_process):
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("XLA_FLAGS", None)  # one device per process
    port = _free_port()
    outs = [tmp_path / f"rank{i}.npz" for i in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(port), str(i), str(outs[i])], cwd=root, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    try:
        results = [p.communicate(timeout=300) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for i, (p, (stdout, stderr)) in enumerate(zip(procs, results)):
        assert p.returncode == 0 and f"OK {i}" in stdout, stderr[-3000:]
    est, sc = one_process
    for out in outs:  # every process holds the whole result
        _check(np.load(out), est, sc)


LOCAL = textwrap.dedent("""
    import sys
    import jax
    import numpy as np
    assert len(jax.devices()) == 2, jax.devices()
    from tests.core.test_distributed import BASES, DISC, FINGER
    from softgrip_jax import Geometric, estimate_batch
    steps = []
    est = estimate_batch(FINGER, DISC, BASES, estimator=Geometric(), chunk_size=4, progress=lambda d, n: steps.append(d))
    n = len(BASES)
    assert steps == [min(8 * k, n) for k in range(1, -(-n // 8) + 1)], steps  # rounds of a 4-base piece per device
    empty = estimate_batch(FINGER, DISC, np.zeros((0, 2), np.float32), estimator=Geometric(), chunk_size=4)
    assert empty.joints.shape == (0, FINGER.n_links + 1, 2) and empty.valid.shape == (0,), empty.joints.shape
    np.savez(sys.argv[1], joints=np.asarray(est.joints), case=np.asarray(est.case), valid=np.asarray(est.valid))
    print("OK")
""")


@pytest.mark.slow
def test_two_local_devices_give_one_device_result(tmp_path, one_process):
    """estimate_batch over two host devices of one process (score's: tests/core/test_score.py)."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2",
               PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", LOCAL, str(tmp_path / "local.npz")], cwd=root, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "OK" in out.stdout, out.stderr[-3000:]
    _check(np.load(tmp_path / "local.npz"), one_process[0])
