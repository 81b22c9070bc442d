"""Exported programs kept with the compilation cache (softgrip_jax._export).

What is checked: the exported path gives the same results as the jitted one (bit for bit); a stale
or broken file falls back silently; a new process with a warm cache traces none of the batch
functions and misses the compilation cache for no program (counted, not timed).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import softgrip_jax
from softgrip_jax import ContactConfig, FingerModel, Geometric, Gripper, PolygonSDF, ScoreWeights
from softgrip_jax import _export
from softgrip_jax._batch import _estimate_batch, _estimate_grasp_batch
from softgrip_jax._score import _refine_batch, _score_one_device

ROOT = Path(__file__).resolve().parents[2]
FINGER = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=5)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=56.0)
DISC = PolygonSDF.regular((0.0, 38.0), 15.0, 16)
POSES = jnp.stack([jnp.linspace(-6.0, 6.0, 8), jnp.linspace(-4.0, 4.0, 8), jnp.linspace(-0.1, 0.1, 8)], axis=-1)
#: Every function wrapped by ``_export.exportable``; their counters summed are the process's.
EXPORTABLE = (_score_one_device, _refine_batch, _estimate_batch, _estimate_grasp_batch)


def _totals() -> _export.ExportInfo:
    return _export.ExportInfo._make(map(sum, zip(*(fn.export_info() for fn in EXPORTABLE))))


@pytest.fixture
def export_cache(tmp_path, monkeypatch):
    """The compilation cache (and so the exports) on in ``tmp_path``; everything put back after."""
    monkeypatch.delenv("SOFTGRIP_JAX_CACHE", raising=False)
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes")
    saved = {n: getattr(jax.config, n) for n in names}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        softgrip_jax.enable_compilation_cache(tmp_path)
    yield tmp_path / _export.EXPORT_SUBFOLDER
    for name, value in saved.items():
        jax.config.update(name, value)
    from jax.experimental.compilation_cache import compilation_cache
    compilation_cache.reset_cache()


def _assert_identical(a, b) -> None:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _score_args():
    return (GRIPPER, DISC, POSES, ScoreWeights(), ContactConfig())


def test_exported_score_equals_the_jitted_one(export_cache) -> None:
    assert _export.active_folder() == export_cache
    before = _score_one_device.export_info()
    exported = _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    assert _score_one_device.export_info() == before._replace(exported=before.exported + 1)  # written to disk
    assert len(list(export_cache.glob("score_share-*.export"))) == 1
    jitted = _score_one_device._jitted(*_score_args(), chunk_size=8, estimator=Geometric())
    _assert_identical(exported, jitted)
    # The public function goes the same way.
    _assert_identical(softgrip_jax.score(GRIPPER, DISC, POSES, method="geometric", chunk_size=8), jitted)


def test_a_broken_or_stale_export_falls_back_silently(export_cache) -> None:
    reference = _score_one_device._jitted(*_score_args(), chunk_size=8, estimator=Geometric())
    _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    (path,) = export_cache.glob("score_share-*.export")
    path.write_bytes(b"not an export")
    _score_one_device._calls.clear()  # as a new process: read the file again
    before = _score_one_device.export_info()
    _assert_identical(_score_one_device(*_score_args(), chunk_size=8, estimator=Geometric()), reference)
    after = _score_one_device.export_info()
    assert after.loaded == before.loaded
    assert after.exported == before.exported + 1  # exported again, over the broken file
    _score_one_device._calls.clear()
    _assert_identical(_score_one_device(*_score_args(), chunk_size=8, estimator=Geometric()), reference)
    assert _score_one_device.export_info().loaded == before.loaded + 1


def test_another_cache_folder_prepares_its_own_exports(export_cache, tmp_path) -> None:
    """The folder is part of each signature's memo: a cache folder configured later gets its own
    files instead of the programs prepared for the first one."""
    _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    other = tmp_path / "other"
    jax.config.update("jax_compilation_cache_dir", str(other))  # the fixture puts it back
    before = _score_one_device.export_info()
    _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    assert _score_one_device.export_info().exported == before.exported + 1
    assert len(list((other / _export.EXPORT_SUBFOLDER).glob("score_share-*.export"))) == 1


@pytest.mark.parametrize("off", ["SOFTGRIP_JAX_CACHE=0", "no cache folder"])
def test_without_the_cache_nothing_is_exported(export_cache, monkeypatch, off) -> None:
    if off == "SOFTGRIP_JAX_CACHE=0":
        monkeypatch.setenv("SOFTGRIP_JAX_CACHE", "0")
    else:
        jax.config.update("jax_compilation_cache_dir", None)  # the fixture puts it back
    assert _export.active_folder() is None
    before = _totals()
    _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    assert _totals() == before
    assert not export_cache.exists()


@pytest.mark.slow
def test_exported_refine_equals_the_jitted_one(export_cache) -> None:
    args = (GRIPPER, DISC, POSES[:2], ScoreWeights(), ContactConfig(), 10, jnp.asarray(0.05), Geometric())
    _assert_identical(_refine_batch(*args), _refine_batch._jitted(*args))
    assert len(list(export_cache.glob("refine_poses-*.export"))) == 1


PLANNER = textwrap.dedent("""
    import json, sys
    import jax, jax.monitoring
    import softgrip_jax
    softgrip_jax.enable_compilation_cache(sys.argv[1])
    import jax.numpy as jnp
    from softgrip_jax import FingerModel, Gripper, PolygonSDF, refine, score
    from softgrip_jax import _batch, _score

    events = {}
    jax.monitoring.register_event_listener(lambda name, **kw: events.__setitem__(name, events.get(name, 0) + 1))
    traced = {"score": 0, "refine": 0}
    score_grasp, refine_one = _score._score_grasp, _score._refine_one
    def counting(name, fn):
        def wrapped(*args, **kwargs):
            traced[name] += 1
            return fn(*args, **kwargs)
        return wrapped
    _score._score_grasp = counting("score", score_grasp)
    _score._refine_one = counting("refine", refine_one)

    finger = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=5)
    gripper = Gripper(left=finger, right=finger, base_separation=56.0)
    obj = PolygonSDF.regular(center=(0.0, 38.0), radius=15.0, n_vertices=16)
    x, y = jnp.meshgrid(jnp.linspace(-10.0, 10.0, 4), jnp.linspace(-10.0, 10.0, 4), indexing="ij")
    poses = jnp.stack([x.ravel(), y.ravel(), jnp.zeros(16)], axis=-1)
    result = score(gripper, obj, poses, method="geometric")
    best = int(jnp.argmax(result.score))
    refined = refine(gripper, obj, poses[best], method="geometric", max_steps=10)
    exportable = (_score._score_one_device, _score._refine_batch, _batch._estimate_batch,
                  _batch._estimate_grasp_batch)
    stats = dict(zip(("loaded", "exported", "fallback"), map(sum, zip(*(f.export_info() for f in exportable)))))
    print(json.dumps({"stats": stats, "traced": traced, "score": float(refined.score.score),
                      "pose": [float(v) for v in refined.pose],
                      "misses": events.get("/jax/compilation_cache/cache_misses", 0),
                      "hits": events.get("/jax/compilation_cache/cache_hits", 0)}))
""")


@pytest.mark.slow
def test_a_new_process_with_a_warm_cache_traces_and_compiles_nothing(tmp_path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "EQX_ON_ERROR": "nan"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env.pop("SOFTGRIP_JAX_CACHE", None)

    def run() -> dict:
        out = subprocess.run([sys.executable, "-c", PLANNER, str(tmp_path / "cache")], env=env, cwd=ROOT,
                             capture_output=True, text=True, timeout=900)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    cold, warm = run(), run()
    assert cold["stats"] == {"loaded": 0, "exported": 2, "fallback": 0}
    assert cold["traced"]["score"] > 0 and cold["traced"]["refine"] > 0
    assert warm["stats"] == {"loaded": 2, "exported": 0, "fallback": 0}
    assert warm["traced"] == {"score": 0, "refine": 0}
    assert warm["misses"] == 0 and warm["hits"] > 0  # every program, small ones included, from the cache
    assert (warm["score"], warm["pose"]) == (cold["score"], cold["pose"])
