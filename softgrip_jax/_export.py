"""Exported programs on disk: a new process calls the batch functions without tracing them again.

JAX's persistent compilation cache (:mod:`softgrip_jax._cache`) skips XLA's compilation, but it is
looked up with the lowered program, so every new process first traces and lowers the Python
program again. For ``refine`` and ``score`` (optimistix's root finders, vmapped) that
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
and the backend. A function that cannot be exported (host callbacks: a caller's own, or equinox's
runtime errors in code outside this package) runs on the ordinary ``jax.jit`` path, silently. Results are those of
the jitted function: the same program, compiled with the same options.

Nothing read from the folder can run Python code. A file is plain data (see "the file format"
below: a JSON header and the serialized StableHLO, never a pickle), read only from a folder and a
file that no other user can write, and checked (size, header, SHA-256, the output structure built
only from this package's classes) before it is deserialized. A file that fails a check is ignored
with one :class:`~softgrip_jax._cache.UntrustedCacheWarning` and exported again; a folder others
can write is not used at all.

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

import dataclasses
import enum
import functools
import hashlib
import inspect
import json
import logging
import os
import stat
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax

from softgrip_jax._cache import UntrustedCacheWarning, untrusted_reason
from softgrip_jax._compile import compiler_options
from softgrip_jax._concurrent import is_traced

#: Subfolder of the compilation cache folder that holds the exported programs.
EXPORT_SUBFOLDER = "softgrip-export"
#: Bumped when the file layout below changes (1 was a pickle, which ran code on reading: never again).
FORMAT = 2

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
    configured = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]  # set at run time
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


def _backend_settings(estimator: object = None) -> str:
    x64 = jax.config.jax_enable_x64  # type: ignore[attr-defined]  # set at run time
    return (f"backend={jax.default_backend()};x64={x64};"
            f"options={sorted(compiler_options(estimator).items())}")


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
        estimator = dict(static).get("estimator")
        ident = "\n".join([self._fn.__module__ + "." + self._fn.__qualname__, _environment(), _backend_settings(estimator),
                           repr(names), str(treedef), repr([(a.shape, str(a.dtype), a.weak_type) for a in avals]),
                           repr(statics)])
        for place in (folder.parent, folder):
            reason = untrusted_reason(place) if place.exists() else None
            if reason is not None:
                warnings.warn(f"softgrip_jax: exported programs not used: {reason}", UntrustedCacheWarning,
                              stacklevel=4)
                return None
        digest = hashlib.sha256(ident.encode()).hexdigest()
        path = folder / f"{self._fn.__name__.strip('_')}-{digest[:40]}.export"
        exported = out_treedef = None
        if path.exists() or path.is_symlink():
            try:
                exported, out_treedef = _read(path, ident)
                self._loaded += 1
            except (OSError, ValueError) as err:  # unreadable, altered, stale or unsafe: exported again
                warnings.warn(f"softgrip_jax: ignoring the cached program {path}: {err}", UntrustedCacheWarning,
                              stacklevel=4)
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
                _write(path, _encode_file(ident, bytes(exported.serialize()), out_treedef))
                self._exported += 1
            except (OSError, ValueError):  # not kept on disk; this process still uses the export
                _log.debug("softgrip_jax: cannot write %s", path, exc_info=True)
        options = compiler_options(estimator) or None
        call = jax.jit(lambda *leaves: exported.call(*leaves), compiler_options=options)
        return call, out_treedef


# -- the file format ----------------------------------------------------------------------------
#
# A file is the line MAGIC, one line of JSON (the header), and the bytes of ``Exported.serialize()``
# (a flatbuffer of StableHLO: data, parsed by jax.export, never run as Python). The header holds the
# signature's ident, the payload's size and SHA-256, and the output structure in JSON
# (:func:`_structure_json`). Reading checks the file (a regular file of this user's that nobody else
# can write, not too large), then the header, then the hash, and only then deserializes; the output
# structure is rebuilt only from classes of this package.

MAGIC = b"softgrip-export\n"
#: Larger files are refused unread (the exports of this package are a few MB).
MAX_FILE_BYTES = 256 * 2**20
MAX_HEADER_BYTES = 2**20


def _encode_file(ident: str, payload: bytes, out_treedef) -> bytes:
    structure = _structure_json(jax.tree_util.tree_unflatten(out_treedef, [_LEAF] * out_treedef.num_leaves))
    if jax.tree_util.tree_structure(_structure_from_json(structure)) != out_treedef:
        raise ValueError("the output structure does not survive its JSON form")
    header = {"format": FORMAT, "ident": ident, "size": len(payload), "sha256": hashlib.sha256(payload).hexdigest(),
              "outputs": structure, "treedef": str(out_treedef)}
    return MAGIC + json.dumps(header, separators=(",", ":")).encode() + b"\n" + payload


def _read(path: Path, ident: str):
    """(Exported, output treedef) from the file at ``path``, or ValueError / OSError saying why not."""
    from jax import export

    data = _read_private(path)
    if not data.startswith(MAGIC):
        raise ValueError("not a softgrip export file (an older format, or altered)")
    end = data.find(b"\n", len(MAGIC), len(MAGIC) + MAX_HEADER_BYTES)
    if end < 0:
        raise ValueError("no header line")
    try:
        header = json.loads(data[len(MAGIC):end])
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"header is not JSON ({err})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT or header.get("ident") != ident:
        raise ValueError("written for another signature or format")
    payload = data[end + 1:]
    if header.get("size") != len(payload) or header.get("sha256") != hashlib.sha256(payload).hexdigest():
        raise ValueError("its content does not match its SHA-256 (truncated or altered)")
    out_treedef = jax.tree_util.tree_structure(_structure_from_json(header.get("outputs")))
    if str(out_treedef) != header.get("treedef"):
        raise ValueError("its output structure does not match its header")
    try:
        exported = export.deserialize(bytearray(payload))
    except Exception as err:  # noqa: BLE001 - whatever the flatbuffer parser raises
        raise ValueError(f"jax.export cannot read it ({type(err).__name__})") from None
    if out_treedef.num_leaves != len(exported.out_avals):  # type: ignore[attr-defined]  # jaxlib has no stub
        raise ValueError("its outputs do not match its program")
    return exported, out_treedef


def _read_private(path: Path) -> bytes:
    """The bytes of ``path``: a regular file (no symbolic link) that only this user can write,
    checked on the open file itself, and at most :data:`MAX_FILE_BYTES`."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags)
    except OSError as err:
        raise OSError(f"cannot open it ({err.strerror}; a symbolic link is refused)") from None
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise ValueError("not a regular file")
        if hasattr(os, "geteuid") and (info.st_uid not in (os.geteuid(), 0) or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)):
            raise ValueError("it belongs to another user or others can write it")
        if info.st_size > MAX_FILE_BYTES:
            raise ValueError(f"larger than {MAX_FILE_BYTES} bytes")
        return f.read(MAX_FILE_BYTES + 1)


class _Leaf:
    """Stands for an array in an output template."""


_LEAF = _Leaf()
_JSON_SCALARS = (bool, int, float, str, type(None))


def _class_path(kind: type) -> str:
    return f"{kind.__module__}:{kind.__qualname__}"


def _package_class(path) -> type:
    """The class named ``module:QualName`` if it is one of this package's equinox modules, named
    tuples or enums, already imported; ValueError otherwise (nothing is imported or called)."""
    if not isinstance(path, str) or ":" not in path:
        raise ValueError(f"bad class name {path!r} in its output structure")
    module_name, qualname = path.split(":", 1)
    module = sys.modules.get(module_name)
    if module is None or module_name.split(".")[0] != __name__.split(".")[0] or "." in qualname:
        raise ValueError(f"its output structure names {path!r}, not a class of this package")
    kind = getattr(module, qualname, None)
    if not isinstance(kind, type) or not (issubclass(kind, (eqx.Module, enum.Enum))
                                          or (issubclass(kind, tuple) and hasattr(kind, "_fields"))):
        raise ValueError(f"its output structure names {path!r}, not a class of this package")
    return kind


def _structure_json(node):
    """A pytree template (arrays replaced by :data:`_LEAF`) as JSON: containers, this package's
    equinox modules and named tuples, and their static fields' plain values and enums."""
    if node is _LEAF:
        return {"leaf": True}
    if isinstance(node, enum.Enum):
        return {"enum": _class_path(type(node)), "value": node.value}
    if isinstance(node, _JSON_SCALARS):
        return {"value": node}
    if isinstance(node, eqx.Module):
        _package_class(_class_path(type(node)))
        return {"module": _class_path(type(node)),
                "fields": {f.name: _structure_json(getattr(node, f.name)) for f in dataclasses.fields(node)}}
    if isinstance(node, tuple) and hasattr(node, "_fields"):
        _package_class(_class_path(type(node)))
        return {"namedtuple": _class_path(type(node)), "items": [_structure_json(v) for v in node]}
    if type(node) in (tuple, list):
        return {type(node).__name__: [_structure_json(v) for v in node]}
    if type(node) is dict and all(isinstance(k, str) for k in node):
        return {"dict": {k: _structure_json(v) for k, v in node.items()}}
    raise ValueError(f"{type(node).__name__} has no JSON form")


def _structure_from_json(data):
    """The template :func:`_structure_json` describes; ValueError for anything else."""
    if not isinstance(data, dict) or len(data) not in (1, 2):
        raise ValueError("malformed output structure")
    if data.get("leaf") is True:
        return _LEAF
    if "value" in data and "enum" not in data:
        if not isinstance(data["value"], _JSON_SCALARS):
            raise ValueError("malformed output structure")
        return data["value"]
    if "enum" in data:
        kind = _package_class(data["enum"])
        if not issubclass(kind, enum.Enum):
            raise ValueError(f"{data['enum']} is not an enum")
        return kind(data["value"])
    if "module" in data:
        kind = _package_class(data["module"])
        fields = data.get("fields")
        names = [f.name for f in dataclasses.fields(kind)] if issubclass(kind, eqx.Module) else None
        if names is None or not isinstance(fields, dict) or sorted(fields) != sorted(names):
            raise ValueError(f"fields of {data['module']} do not match the class")
        # As equinox's own unflatten does: a new instance with its fields set, no __init__ run.
        node = object.__new__(kind)
        for name in names:
            object.__setattr__(node, name, _structure_from_json(fields[name]))
        return node
    if "namedtuple" in data:
        kind = _package_class(data["namedtuple"])
        items = data.get("items")
        if not isinstance(items, list) or len(items) != len(getattr(kind, "_fields", ())):
            raise ValueError(f"items of {data['namedtuple']} do not match the class")
        return kind(*map(_structure_from_json, items))
    for name, container in (("tuple", tuple), ("list", list)):
        if name in data and isinstance(data[name], list):
            return container(map(_structure_from_json, data[name]))
    if "dict" in data and isinstance(data["dict"], dict):
        return {k: _structure_from_json(v) for k, v in data["dict"].items()}
    raise ValueError("malformed output structure")


def _write(path: Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` atomically (a temporary file renamed), so that a process
    reading it never sees half a file."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
