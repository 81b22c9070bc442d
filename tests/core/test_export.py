"""Exported programs kept with the compilation cache (softgrip_jax._export).

What is checked: the exported path gives the same results as the jitted one (integers and flags
exactly, floats to float rounding: the exported program is compiled from its deserialized StableHLO
inside a call, and XLA:CPU's loop emitter has been seen to round a last bit differently); a file
that is broken, altered, planted (a pickle that would run code), foreign (naming classes outside the
package), writable by others or behind a link is ignored with one warning and exported again, and a
folder others can write is not used; a new process with a warm cache traces none of the batch
functions and misses the compilation cache for no program (counted, not timed).
"""

from __future__ import annotations

import json
import os
import stat
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
from softgrip_jax._cache import UntrustedCacheWarning
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


def _assert_same_results(a, b) -> None:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        assert x.shape == y.shape and x.dtype == y.dtype
        if jnp.issubdtype(x.dtype, jnp.floating):  # (infinities must match exactly)
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-5)
        else:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _score_args():
    return (GRIPPER, DISC, POSES, ScoreWeights(), ContactConfig(), None)


def test_exported_score_equals_the_jitted_one(export_cache) -> None:
    assert _export.active_folder() == export_cache
    before = _score_one_device.export_info()
    exported = _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    assert _score_one_device.export_info() == before._replace(exported=before.exported + 1)  # written to disk
    assert len(list(export_cache.glob("score_share-*.export"))) == 1
    jitted = _score_one_device._jitted(*_score_args(), chunk_size=8, estimator=Geometric())
    _assert_same_results(exported, jitted)
    # The public function goes the same way.
    _assert_same_results(softgrip_jax.score(GRIPPER, DISC, POSES, estimator=Geometric(), chunk_size=8), jitted)


def _ignored_with_one_warning(path, reference, match: str) -> None:
    """Reading ``path`` again (as a new process would) ignores it with one warning that names it and
    ``match``, returns the jitted results, and writes a good export in its place."""
    _score_one_device._calls.clear()  # as a new process: read the file again
    before = _score_one_device.export_info()
    with pytest.warns(UntrustedCacheWarning, match=match) as caught:
        _assert_same_results(_score_one_device(*_score_args(), chunk_size=8, estimator=Geometric()), reference)
    assert len([w for w in caught if issubclass(w.category, UntrustedCacheWarning)]) == 1
    assert str(path) in str(caught[0].message)
    after = _score_one_device.export_info()
    assert after.loaded == before.loaded
    assert after.exported == before.exported + 1  # exported again, over the bad file
    _score_one_device._calls.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("error", UntrustedCacheWarning)
        _assert_same_results(_score_one_device(*_score_args(), chunk_size=8, estimator=Geometric()), reference)
    assert _score_one_device.export_info().loaded == before.loaded + 1


@pytest.fixture
def written_export(export_cache):
    """(path of the score's export file, the jitted reference result)."""
    reference = _score_one_device._jitted(*_score_args(), chunk_size=8, estimator=Geometric())
    _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    (path,) = export_cache.glob("score_share-*.export")
    return path, reference


class _Planted:
    """What an attacker writes: a pickle that runs code (here: makes a folder) when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (str(self.marker),)


def test_a_pickle_planted_in_the_cache_never_runs(written_export, tmp_path) -> None:
    """The first file format was a pickle: whoever could write the folder ran code in every process
    that read it. Now the file is data, and a planted pickle is ignored unread."""
    import pickle

    path, reference = written_export
    marker = tmp_path / "code-ran"
    path.write_bytes(pickle.dumps({"ident": "x", "exported": _Planted(marker), "template": _Planted(marker)}))
    _ignored_with_one_warning(path, reference, "not a softgrip export")
    assert not marker.exists()


def _rewrite_header(path: Path, change) -> None:
    data = path.read_bytes()
    end = data.index(b"\n", len(_export.MAGIC))
    header = json.loads(data[len(_export.MAGIC):end])
    change(header)
    path.write_bytes(_export.MAGIC + json.dumps(header).encode() + data[end:])


@pytest.fixture(scope="module")
def good_export(tmp_path_factory):
    """(bytes of a good export file of the score, its ident), written once for the module."""
    folder = tmp_path_factory.mktemp("good")
    saved = jax.config.jax_compilation_cache_dir, os.environ.get("SOFTGRIP_JAX_CACHE")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    os.environ.pop("SOFTGRIP_JAX_CACHE", None)  # (the tests' conftest turns it off by default)
    try:
        _score_one_device._calls.clear()
        _score_one_device(*_score_args(), chunk_size=8, estimator=Geometric())
    finally:
        jax.config.update("jax_compilation_cache_dir", saved[0])
        if saved[1] is not None:
            os.environ["SOFTGRIP_JAX_CACHE"] = saved[1]
        _score_one_device._calls.clear()
    (path,) = (folder / _export.EXPORT_SUBFOLDER).glob("score_share-*.export")
    data = path.read_bytes()
    end = data.index(b"\n", len(_export.MAGIC))
    return data, json.loads(data[len(_export.MAGIC):end])["ident"]


def _with_header(data: bytes, change) -> bytes:
    end = data.index(b"\n", len(_export.MAGIC))
    header = json.loads(data[len(_export.MAGIC):end])
    change(header)
    return _export.MAGIC + json.dumps(header).encode() + data[end:]


def _flip(data: bytes, at: int) -> bytes:
    out = bytearray(data)
    out[at] ^= 0xFF
    return bytes(out)


def test_a_good_export_file_reads_back(good_export, tmp_path) -> None:
    data, ident = good_export
    (path := tmp_path / "a.export").write_bytes(data)
    exported, out_treedef = _export._read(path, ident)
    assert out_treedef.num_leaves == len(exported.out_avals)
    with pytest.raises(ValueError, match="another signature"):
        _export._read(path, ident + "x")


@pytest.mark.parametrize(("alter", "match"), [
    (lambda d: _flip(d, -100), "SHA-256"),  # one byte of the serialized program
    (lambda d: d[:-10], "SHA-256"),  # truncated
    (lambda d: _with_header(d, lambda h: h["outputs"].update(module="os:system")), "not a class of this package"),
    (lambda d: _with_header(d, lambda h: h["outputs"].update(module="subprocess:Popen")), "not a class of this package"),
    (lambda d: _with_header(d, lambda h: h["outputs"].update(module="builtins:eval")), "not a class of this package"),
    (lambda d: _with_header(d, lambda h: h["outputs"].update(module="softgrip_jax._export:_Leaf")),
     "not a class of this package"),
    (lambda d: _with_header(d, lambda h: h["outputs"]["fields"].pop("valid")), "do not match the class"),
    (lambda d: _with_header(d, lambda h: h.update(treedef="PyTreeDef(*)")), "output structure does not match"),
    (lambda d: d[:len(_export.MAGIC)] + b"[1, 2\n" + d[len(_export.MAGIC):], "not JSON"),
    (lambda d: d[:len(_export.MAGIC) + 5], "no header"),
], ids=["program-byte", "truncated", "os.system", "Popen", "eval", "private-class", "missing-field", "treedef",
        "bad-json", "no-header"])
def test_an_altered_export_file_is_refused_before_it_is_deserialized(good_export, tmp_path, alter, match) -> None:
    """Even with a matching hash, the output structure may only name this package's equinox modules,
    named tuples and enums; nothing is imported or called to check it."""
    data, ident = good_export
    (path := tmp_path / "a.export").write_bytes(alter(data))
    with pytest.raises(ValueError, match=match):
        _export._read(path, ident)


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX owners and modes")
def test_an_export_file_others_can_write_or_behind_a_link_is_refused(good_export, tmp_path) -> None:
    data, ident = good_export
    (path := tmp_path / "a.export").write_bytes(data)
    path.chmod(0o666)
    with pytest.raises(ValueError, match="others can write it"):
        _export._read(path, ident)
    path.chmod(0o600)
    (link := tmp_path / "b.export").symlink_to(path)
    with pytest.raises(OSError, match="symbolic link"):
        _export._read(link, ident)
    fifo = tmp_path / "c.export"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):  # opened without blocking, refused
        _export._read(fifo, ident)
    if os.geteuid() == 0:
        os.chown(path, 4242, 4242)
        with pytest.raises(ValueError, match="another user"):
            _export._read(path, ident)


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX owners and modes")
def test_an_export_folder_others_can_write_is_not_used(written_export) -> None:
    path, reference = written_export
    path.parent.chmod(0o777)
    _score_one_device._calls.clear()
    before = _score_one_device.export_info()
    with pytest.warns(UntrustedCacheWarning, match="writable by other users"):
        _assert_same_results(_score_one_device(*_score_args(), chunk_size=8, estimator=Geometric()), reference)
    after = _score_one_device.export_info()
    assert (after.loaded, after.exported, after.fallback) == (before.loaded, before.exported, before.fallback + 1)


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
    args = (GRIPPER, DISC, POSES[:2], ScoreWeights(), ContactConfig(), None, 10, jnp.asarray(0.025),
            (jnp.asarray(2.0), jnp.asarray(0.125)), Geometric())
    _assert_same_results(_refine_batch(*args), _refine_batch._jitted(*args))
    assert len(list(export_cache.glob("refine_poses-*.export"))) == 1


PLANNER = textwrap.dedent("""
    import json, sys
    import jax, jax.monitoring
    import softgrip_jax
    softgrip_jax.enable_compilation_cache(sys.argv[1])
    import jax.numpy as jnp
    from softgrip_jax import FingerModel, Geometric, Gripper, PolygonSDF, refine, score
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
    result = score(gripper, obj, poses, estimator=Geometric())
    best = int(jnp.argmax(result.score))
    refined = refine(gripper, obj, poses[best], estimator=Geometric(), max_steps=10)
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
