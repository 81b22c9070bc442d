"""JAX's persistent compilation cache for softgrip-jax: compile once per machine, not once per process.

Every compiled entry point (``score``, ``estimate_batch``, ``refine``, the calibration fit without a
progress bar, ...) takes seconds to tens of seconds to compile. With the cache on, a new Python
process that calls them with shapes it has seen before loads the compiled programs from disk.

JAX refuses to store a program that calls back into Python (``jax.debug.callback``,
``jax.pure_callback``, equinox's runtime errors). The core's programs contain none, whatever
``EQX_ON_ERROR`` is: its solvers run with ``throw=False`` and report failures per candidate (a
:class:`~softgrip_jax.Status`), and its implicit gradients (the first contact, the mechanics
equilibrium) use JAX's ``custom_root`` with dense solves instead of lineax, whose checks are
callbacks under reverse mode. Only a progress bar adds one (``softgrip_calib.fit.fit(progress=True)``).

The cache holds compiled machine code, which JAX loads and runs. A folder that another user can
write is therefore refused (:func:`untrusted_reason`, :class:`UntrustedCacheWarning`): the cache is
turned off instead, with one warning, whoever configured it.
"""

from __future__ import annotations

import os
import stat
import warnings
from pathlib import Path

#: Environment variable that turns :func:`enable_compilation_cache` off (``0``).
DISABLE_VARIABLE = "SOFTGRIP_JAX_CACHE"
#: Programs that compile faster than this (s) are not written. JAX's own default is 1 s, which
#: leaves out the dozens of small programs that eager operations (slicing, concatenating the parts
#: of a batch, building poses) compile in every new process; reading them back is faster.
MIN_COMPILE_SECONDS = 0.0


def default_cache_dir() -> Path:
    """The per-user cache folder: ``$JAX_COMPILATION_CACHE_DIR`` when set, else the platform's user
    cache directory (``platformdirs``: ``$XDG_CACHE_HOME/softgrip-jax/jax``, by default
    ``~/.cache/softgrip-jax/jax`` on Linux; ``~/Library/Caches/softgrip-jax/jax`` on macOS)."""
    explicit = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if explicit:
        return Path(explicit)
    import platformdirs

    return platformdirs.user_cache_path("softgrip-jax", appauthor=False) / "jax"


def equinox_errors_cacheable() -> bool:
    """Whether equinox's runtime checks compile without host callbacks in this process
    (``EQX_ON_ERROR`` was ``nan`` or ``off`` when equinox was imported)."""
    from equinox._config import EQX_ON_ERROR  # read once, at equinox's import

    return EQX_ON_ERROR in ("nan", "off")


def enable_compilation_cache(path: str | os.PathLike[str] | None = None) -> Path | None:
    """Keep compiled programs on disk, so that a new process starts in seconds instead of compiling.

    Call it once, before the first compiled call (calling it again is harmless). It sets JAX's
    ``jax_compilation_cache_dir`` and writes every compiled program (:data:`MIN_COMPILE_SECONDS`).
    ``SOFTGRIP_JAX_CACHE=0`` in the environment turns it off, and a cache directory already
    configured (``jax.config`` or ``JAX_COMPILATION_CACHE_DIR``) is kept.

    The batch functions (``score``, ``refine``, ``estimate_batch``, ``estimate_grasp_batch``) also
    keep their exported programs in the folder's ``softgrip-export`` subfolder
    (:mod:`softgrip_jax._export`): a new process with the same shapes and settings neither traces
    nor compiles them. They follow JAX's configured cache folder at each call, whoever set it, and
    stop with ``SOFTGRIP_JAX_CACHE=0``.

    Args:
        path: the cache folder; by default :func:`default_cache_dir` (a per-user cache directory).

    Returns:
        The folder in use, or None when the cache is off (``SOFTGRIP_JAX_CACHE=0``, or a folder that
        cannot be created: the program then runs, compiling as without the cache).

    Example:
        >>> import tempfile, softgrip_jax
        >>> folder = softgrip_jax.enable_compilation_cache(tempfile.mkdtemp())  # doctest: +SKIP
    """
    import jax

    if os.environ.get(DISABLE_VARIABLE, "1") == "0":
        return None
    configured = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]  # set at run time
    keep = bool(configured) and path is None
    folder = Path(configured) if keep else Path(path) if path is not None else default_cache_dir()
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as err:
        warnings.warn(f"softgrip_jax: compilation cache off, cannot create {folder}: {err}", stacklevel=2)
        return None
    reason = untrusted_reason(folder)
    if reason is not None:
        # The cache holds compiled machine code that JAX loads and runs: a folder another user can
        # write is a way into this process. Off, also when someone else configured it.
        warnings.warn(f"softgrip_jax: compilation cache off: {reason}", UntrustedCacheWarning, stacklevel=2)
        if keep:
            jax.config.update("jax_compilation_cache_dir", None)
            _reset_cache_backend(jax)
        return None
    if not keep:
        jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    if not keep:
        _reset_cache_backend(jax)
    return folder


class CacheWarning(UserWarning):
    """A compiled program that the persistent cache will not hold (see :func:`enable_compilation_cache`)."""


class UntrustedCacheWarning(CacheWarning):
    """A cache folder or file that is not used because someone else could have written it, or a
    cache file that failed its integrity check (it is ignored and written anew)."""


def untrusted_reason(path: Path) -> str | None:
    """Why the cache folder or file ``path`` may not be trusted with code, or None when it may.

    Trusted: owned by this process's user (or by root), not a symbolic link when a file, and
    writable by nobody else (no group or world write bit). The compilation cache holds compiled
    machine code that JAX loads and runs, and the exported programs are compiled from what is read
    back: whoever can write there runs code in every process that uses the folder. On a system
    without POSIX owners (Windows) nothing is checked. A folder this package creates is made 0700.
    """
    if not hasattr(os, "geteuid"):
        return None
    try:
        info = path.lstat()
    except OSError as err:
        return f"cannot read {path}: {err.strerror}"
    if stat.S_ISLNK(info.st_mode):
        try:
            target = path.resolve(strict=True)
        except OSError as err:
            return f"{path} is a symbolic link that does not resolve: {err.strerror}"
        if not path.is_dir():
            return f"{path} is a symbolic link (a cache file must be a regular file)"
        return untrusted_reason(target)
    if not (stat.S_ISDIR(info.st_mode) or stat.S_ISREG(info.st_mode)):
        return f"{path} is neither a folder nor a regular file"
    if info.st_uid not in (os.geteuid(), 0):
        return (f"{path} belongs to another user (uid {info.st_uid}); use a cache folder of your own "
                f"(JAX_COMPILATION_CACHE_DIR, or softgrip_jax.enable_compilation_cache(path))")
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return (f"{path} is writable by other users (mode {stat.S_IMODE(info.st_mode):o}), who could put "
                f"code there; make it yours alone (chmod go-w '{path}') or use another folder")
    return None


def _reset_cache_backend(jax) -> None:
    """JAX decides once, at the first compilation, whether (and where) it caches: a folder set after
    that needs its cache state reset (``jax.experimental.compilation_cache``)."""
    try:
        from jax.experimental.compilation_cache import compilation_cache
    except ImportError:  # a JAX without it: the folder applies from the next process on
        return
    compilation_cache.reset_cache()
