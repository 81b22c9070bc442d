"""Exported programs on disk: a new process calls the batch functions without tracing them again.

JAX's persistent compilation cache (:mod:`softgrip_jax._cache`) skips XLA's compilation, but it is
looked up with the lowered program, so every new process first traces and lowers the Python
program again. For ``refine`` and ``score`` (optimistix's BFGS and root finders, vmapped) that
tracing is most of a new process's start-up.

With the cache on, the batch functions wrapped by :class:`exportable` go through ``jax.export``
instead: the first call with a new signature traces the function once, exports it (StableHLO) and
writes the serialized export to ``<cache folder>/softgrip-export/``; a later process with the same
signature reads it back and calls it, without tracing. The compiled program then comes from the
persistent cache as before. A signature is the function, the shapes, dtypes and weak types of the
array arguments, the tree structure of the arguments (which holds every static field of the models
and configs), the static arguments (an estimator by its class, name and settings:
:func:`static_ident`), and the versions that decide the program: jax, jaxlib,
equinox, lineax, optimistix, a hash of this package's source files, ``EQX_ON_ERROR``, the x64 flag
and the backend. A file that does not match, does not load, or a function that cannot be exported
(host callbacks, e.g. equinox's runtime errors without ``EQX_ON_ERROR=nan``) falls back to the
ordinary ``jax.jit`` path, silently. Results are those of the jitted function: the same program,
compiled with the same options.

"The cache on" is read from JAX's configuration at every call (:func:`active_folder`): exports are
kept while ``jax.config.jax_compilation_cache_dir`` is set (by
:func:`~softgrip_jax.enable_compilation_cache`, ``JAX_COMPILATION_CACHE_DIR`` or
``jax.config.update``) and ``SOFTGRIP_JAX_CACHE`` is not ``0``. Each wrapped function remembers
what it prepared per (folder, signature), so a changed folder prepares its signatures again, and
counts what it did (:meth:`exportable.export_info`). The module itself holds no mutable state.

Inside another trace (``jit``, ``grad``, ``vmap`` of a batch function) the wrapped function is the
jitted one, unchanged.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import logging
import os
import pickle
import tempfile
import threading
from pathlib import Path
from typing import NamedTuple

import jax

from softgrip_jax._compile import compiler_options
from softgrip_jax._concurrent import is_traced

#: Subfolder of the compilation cache folder that holds the exported programs.
EXPORT_SUBFOLDER = "softgrip-export"
#: Bumped when the file layout below changes.
FORMAT = 1

_log = logging.getLogger(__name__)


class ExportInfo(NamedTuple):
    """What one :class:`exportable` function did in this process (like ``functools``'
    ``cache_info()``), counted per signature: ``loaded`` (read from disk), ``exported`` (written),
    ``fallback`` (signatures that run on the jitted path)."""

    loaded: int
    exported: int
    fallback: int


def active_folder() -> Path | None:
    """The folder for exported programs, from JAX's configuration at this call:
    ``<jax_compilation_cache_dir>/EXPORT_SUBFOLDER``; None (exporting off) when JAX's cache folder
    is unset or ``SOFTGRIP_JAX_CACHE=0``."""
    if os.environ.get("SOFTGRIP_JAX_CACHE", "1") == "0":
        return None
    configured = jax.config.jax_compilation_cache_dir
    if not configured:
        return None
    return Path(configured) / EXPORT_SUBFOLDER


@functools.cache
def _environment() -> str:
    """The versions and settings an exported program depends on, as one string."""
    from importlib.metadata import PackageNotFoundError, version

    parts = [f"format={FORMAT}"]
    for name in ("jax", "jaxlib", "equinox", "lineax", "optimistix"):
        try:
            parts.append(f"{name}={version(name)}")
        except PackageNotFoundError:
            parts.append(f"{name}=?")
    source = hashlib.sha256()
    package = Path(__file__).resolve().parent
    for path in sorted(package.glob("*.py")):
        source.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    parts.append(f"source={source.hexdigest()}")
    from equinox._config import EQX_ON_ERROR

    parts.append(f"EQX_ON_ERROR={EQX_ON_ERROR}")
    return ";".join(parts)


def static_ident(value) -> str | None:
    """A static argument as it keys an exported program: numbers and strings by their repr; an
    object of this package (an estimator) by its class's module and qualified name, its ``name`` and
    its repr (which shows every setting that differs from its default, e.g.
    ``Mechanics(config=MechanicsConfig(max_steps=8))``).

    None for an object of a class defined elsewhere (an estimator of the user's): its code is not in
    the source hash above, so a program exported for it could outlive a change to it. Such a
    signature runs on the jitted path instead (whose compilation cache keys the lowered program).
    """
    if isinstance(value, (bool, int, float, str, type(None))):
        return repr(value)
    kind = type(value)
    if kind.__module__.split(".")[0] != __name__.split(".")[0]:
        return None
    name = getattr(value, "name", None)
    return f"{kind.__module__}.{kind.__qualname__}" + (f"[{name}]" if isinstance(name, str) else "") + f":{value!r}"


def _backend_settings() -> str:
    return (f"backend={jax.default_backend()};x64={jax.config.jax_enable_x64};"
            f"options={sorted(compiler_options().items())}")


class exportable:  # noqa: N801 - used like jax.jit
    """A :class:`~softgrip_jax._compile.tuned_jit` function that, with the compilation cache on,
    runs through ``jax.export`` programs kept on disk (see the module docstring). Called like the
    jitted function, with the same results; its attributes (``lower``, ...) are the jitted one's."""

    def __init__(self, jitted, static_argnames: tuple[str, ...]):
        functools.update_wrapper(self, jitted._fn, updated=())
        self._jitted = jitted
        self._fn = jitted._fn  # the Python function (tuned_jit keeps it)
        self._signature = inspect.signature(self._fn)
        self._static = tuple(static_argnames)
        # (folder, signature) -> (compiled call, output structure), or None (the jitted path)
        self._calls: dict = {}
        self._lock = threading.Lock()
        self._loaded = self._exported = self._fallback = 0

    def export_info(self) -> ExportInfo:
        """How many signatures this function loaded from disk, exported, or runs jitted."""
        with self._lock:
            return ExportInfo(self._loaded, self._exported, self._fallback)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._jitted, name)

    def __call__(self, *args, **kwargs):
        folder = active_folder()
        if folder is None or is_traced((args, kwargs)):
            return self._jitted(*args, **kwargs)
        bound = self._signature.bind(*args, **kwargs)
        bound.apply_defaults()
        static = tuple((k, v) for k, v in bound.arguments.items() if k in self._static)
        dynamic = tuple((k, v) for k, v in bound.arguments.items() if k not in self._static)
        names = tuple(k for k, _ in dynamic)
        leaves, treedef = jax.tree_util.tree_flatten(tuple(v for _, v in dynamic))
        try:
            avals = tuple(jax.typeof(x) for x in leaves)
            key = (folder, names, treedef, tuple((a.shape, a.dtype, a.weak_type) for a in avals), static)
            hash(key)
        except Exception:  # noqa: BLE001 - an argument this path does not handle: the jitted path
            return self._jitted(*args, **kwargs)
        entry = self._calls.get(key, False)
        if entry is False:
            with self._lock:
                entry = self._calls.get(key, False)
                if entry is False:
                    entry = self._prepare(folder, names, static, treedef, avals)
                    self._calls[key] = entry
                    if entry is None:
                        self._fallback += 1
        if entry is None:
            return self._jitted(*args, **kwargs)
        call, out_treedef = entry
        return jax.tree_util.tree_unflatten(out_treedef, call(*leaves))

    # -- building -------------------------------------------------------------------------------

    def _flat(self, names, static, treedef):
        """The function of the flat array leaves that returns the flat output leaves; records the
        output structure in ``out`` when traced."""
        out = {}
        fn = self._fn

        def flat(*leaves):
            values = jax.tree_util.tree_unflatten(treedef, leaves)
            result = fn(**dict(zip(names, values)), **dict(static))
            out_leaves, out["treedef"] = jax.tree_util.tree_flatten(result)
            return out_leaves

        return flat, out

    def _prepare(self, folder: Path, names, static, treedef, avals):
        """(compiled call, output structure) for a signature, from disk or exported now; None when
        this signature runs on the jitted path. Called with ``self._lock`` held."""
        try:
            from jax import export
        except ImportError:
            return None
        statics = [(k, static_ident(v)) for k, v in static]
        if any(ident is None for _, ident in statics):  # e.g. an estimator defined outside this package
            return None
        ident = "\n".join([self._fn.__module__ + "." + self._fn.__qualname__, _environment(), _backend_settings(),
                           repr(names), str(treedef), repr([(a.shape, str(a.dtype), a.weak_type) for a in avals]),
                           repr(statics)])
        digest = hashlib.sha256(ident.encode()).hexdigest()
        path = folder / f"{self._fn.__name__.strip('_')}-{digest[:40]}.export"
        exported = out_treedef = None
        try:
            if path.is_file():
                stored = pickle.loads(path.read_bytes())
                if stored.get("ident") == ident:
                    exported = export.deserialize(bytearray(stored["exported"]))
                    out_treedef = jax.tree_util.tree_structure(stored["template"])
                    if out_treedef.num_leaves != len(exported.out_avals):
                        exported = None
                    else:
                        self._loaded += 1
        except Exception:  # noqa: BLE001 - an unreadable or stale file: export again
            _log.debug("softgrip_jax: cannot load %s", path, exc_info=True)
            exported = None
        if exported is None:
            try:
                flat, out = self._flat(names, static, treedef)
                specs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in avals]
                exported = export.export(jax.jit(flat))(*specs)
                out_treedef = out["treedef"]
            except Exception:  # noqa: BLE001 - e.g. host callbacks, which export refuses
                _log.debug("softgrip_jax: %s not exported, it runs jitted", self._fn.__name__, exc_info=True)
                return None
            try:
                template = jax.tree_util.tree_unflatten(out_treedef, list(range(out_treedef.num_leaves)))
                payload = pickle.dumps({"ident": ident, "exported": bytes(exported.serialize()), "template": template})
                if jax.tree_util.tree_structure(pickle.loads(payload)["template"]) == out_treedef:
                    _write(path, payload)
                    self._exported += 1
            except Exception:  # noqa: BLE001 - not kept on disk; this process still uses the export
                _log.debug("softgrip_jax: cannot write %s", path, exc_info=True)
        options = compiler_options() or None
        call = jax.jit(lambda *leaves: exported.call(*leaves), compiler_options=options)
        return call, out_treedef


def _write(path: Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` atomically (a temporary file renamed), so that a process
    reading it never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
