"""The persistent compilation cache: ``enable_compilation_cache`` and programs the cache can hold.

JAX does not write a program with host callbacks to the cache, so every compiled entry point is
checked for them in its lowered text (no compilation needed).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

import softgrip_jax
from softgrip_jax import ContactConfig, FingerModel, Geometric, Gripper, Mechanics, MechanicsConfig, PolygonSDF, ScoreWeights
from softgrip_jax._cache import CacheWarning, UntrustedCacheWarning, default_cache_dir

ROOT = Path(__file__).resolve().parents[2]
FINGER = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
GRIPPER = Gripper(left=FINGER, right=FINGER, base_separation=56.0)
DISC = PolygonSDF.regular((0.0, 38.0), 15.0, 32)


@pytest.fixture
def restore_cache_config():
    """Put JAX's cache settings back after a test that changes them."""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes")
    saved = {n: getattr(jax.config, n) for n in names}
    yield
    for name, value in saved.items():
        jax.config.update(name, value)
    from jax.experimental.compilation_cache import compilation_cache
    compilation_cache.reset_cache()


def test_enable_compilation_cache_uses_the_given_folder(tmp_path, restore_cache_config, monkeypatch) -> None:
    monkeypatch.delenv("SOFTGRIP_JAX_CACHE", raising=False)
    folder = tmp_path / "a" / "b"
    with warnings.catch_warnings():  # no CacheWarning, whatever EQX_ON_ERROR is
        warnings.simplefilter("error", softgrip_jax.CacheWarning)
        assert softgrip_jax.enable_compilation_cache(folder) == folder
    assert folder.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(folder)
    # A program compiled now is written there (the threshold lowered so that a tiny one counts).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.jit(lambda x: jnp.sin(x) * 3.25 + 17.0)(jnp.arange(7.0)).block_until_ready()
    assert any(folder.iterdir())


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX owners and modes")
@pytest.mark.parametrize("configured", [False, True], ids=["given", "configured-elsewhere"])
def test_a_cache_folder_others_can_write_is_refused(tmp_path, restore_cache_config, monkeypatch, configured) -> None:
    """The cache holds machine code that JAX runs: a folder another user can write is never used,
    whoever named it, and the program runs without a cache."""
    monkeypatch.delenv("SOFTGRIP_JAX_CACHE", raising=False)
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    if configured:
        jax.config.update("jax_compilation_cache_dir", str(shared))
    with pytest.warns(UntrustedCacheWarning, match="writable by other users"):
        assert softgrip_jax.enable_compilation_cache(None if configured else shared) is None
    assert jax.config.jax_compilation_cache_dir in (None, "")


def test_a_new_cache_folder_is_made_private(tmp_path, restore_cache_config, monkeypatch) -> None:
    monkeypatch.delenv("SOFTGRIP_JAX_CACHE", raising=False)
    old = os.umask(0o002)  # a umask that would make a group-writable folder
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CacheWarning)
            warnings.simplefilter("error", UntrustedCacheWarning)
            folder = softgrip_jax.enable_compilation_cache(tmp_path / "new")
    finally:
        os.umask(old)
    assert folder == tmp_path / "new"
    assert (folder.stat().st_mode & 0o077) == 0


def test_enable_compilation_cache_can_be_turned_off(tmp_path, restore_cache_config, monkeypatch) -> None:
    monkeypatch.setenv("SOFTGRIP_JAX_CACHE", "0")
    before = jax.config.jax_compilation_cache_dir
    assert softgrip_jax.enable_compilation_cache(tmp_path / "off") is None
    assert not (tmp_path / "off").exists()
    assert jax.config.jax_compilation_cache_dir == before


def test_default_cache_dir_follows_the_environment(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    if sys.platform.startswith("linux"):
        assert default_cache_dir() == tmp_path / "softgrip-jax" / "jax"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "explicit"))
    assert default_cache_dir() == tmp_path / "explicit"


def _callbacks(lowered) -> int:
    return lowered.as_text().count("callback")


def test_score_and_estimate_batch_compile_without_host_callbacks() -> None:
    from softgrip_jax._batch import _estimate_batch
    from softgrip_jax._score import _score_one_device

    poses = jnp.zeros((4, 3))
    for estimator in (Geometric(), Mechanics(MechanicsConfig())):
        lowered = _score_one_device.lower(GRIPPER, DISC, poses, ScoreWeights(), ContactConfig(), None, 4, estimator)
        assert _callbacks(lowered) == 0, estimator.name
    bases = jnp.zeros((4, 2))
    lowered = _estimate_batch.lower(FINGER, DISC, bases, ContactConfig(), 4, Geometric())
    assert _callbacks(lowered) == 0


def test_refine_geometric_compiles_without_host_callbacks() -> None:
    """The README planner's refine: a gradient through the first-contact root (custom_root) whatever
    EQX_ON_ERROR says."""
    from softgrip_jax._score import _refine_batch

    steps = (jnp.asarray(2.0), jnp.asarray(0.125))  # the compass search's first and last step (mm)
    lowered = _refine_batch.lower(GRIPPER, DISC, jnp.zeros((1, 3)), ScoreWeights(), ContactConfig(),
                                  None, 4, jnp.asarray(0.05), steps, Geometric())
    assert _callbacks(lowered) == 0


@pytest.mark.slow
def test_refine_mechanics_compiles_without_host_callbacks_whatever_eqx_on_error() -> None:
    """A gradient through the mechanics equilibrium (implicit, by custom_root, not lineax): no host
    callback with EQX_ON_ERROR=raise (equinox's default) either. A fresh process per value, since
    equinox reads the variable at import."""
    script = textwrap.dedent("""
        import jax.numpy as jnp
        from softgrip_jax import ContactConfig, FingerModel, Gripper, Mechanics, MechanicsConfig, PolygonSDF, ScoreWeights
        from softgrip_jax._cache import equinox_errors_cacheable
        from softgrip_jax._score import _refine_batch
        f = FingerModel(length=52.0, theta_entire=0.55, half_thickness=4.0, n_links=10)
        g = Gripper(left=f, right=f, base_separation=56.0)
        lowered = _refine_batch.lower(g, PolygonSDF.regular((0.0, 38.0), 15.0, 32), jnp.zeros((1, 3)),
                                      ScoreWeights(), ContactConfig(), None, 4, jnp.asarray(0.05),
                                      (jnp.asarray(2.0), jnp.asarray(0.125)), Mechanics(MechanicsConfig()))
        print(equinox_errors_cacheable(), lowered.as_text().count("callback"))
    """)
    counts = {}
    for mode in ("nan", "raise"):
        env = {**os.environ, "EQX_ON_ERROR": mode, "PYTHONPATH": str(ROOT)}
        out = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True, text=True,
                             check=True, timeout=600)
        counts[mode] = out.stdout.split()
    assert counts["nan"] == ["True", "0"]
    assert counts["raise"] == ["False", "0"]


def test_fit_compiles_without_host_callbacks_unless_a_progress_bar_is_shown() -> None:
    import numpy as np

    from softgrip_calib.fit import _solve, _stack, _unknowns
    from tests.calib.test_fit import observation, start_profile

    rng = np.random.default_rng(3)
    start = start_profile(0.5, 0.5)
    with jax.enable_x64(True):
        y0, fixed, free = _unknowns(start, ["theta_entire"])
        groups, _ = _stack([observation(rng, "pair 1")])
        texts = {progress: _solve.lower(y0, free, fixed, groups, jnp.asarray(1.0, jnp.float64),
                                        n_links=start.fingers["left"].n_links, config=ContactConfig(),
                                        estimator=Geometric(), loss="huber",
                                        max_steps=10, progress=progress).as_text()
                 for progress in (False, True)}
    assert texts[False].count("callback") == 0
    assert texts[True].count("callback") > 0
