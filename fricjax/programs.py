"""Traced programs kept on disk, so that a new process neither traces nor lowers them.

jax's persistent compilation cache (:func:`fricjax.api.enable_compilation_cache`) keeps
the compiled executables, but its key is the lowered program: every new process still
traces the Python code to a jaxpr and lowers it to StableHLO before it can look the
executable up. For the output-error fit of the seed model with its candidate terms, that
is most of a warm ``fricjax diagnose``: the simulator is traced under ``vmap`` and ``jvp``
(about 12 s of tracing for a 1 s record, where the fit itself runs for 5 s).

:func:`stored` wraps a function like ``equinox.filter_jit`` (array leaves traced,
everything else static). When a store folder is set (:func:`set_store`; the CLI sets it
beside the compilation cache), the first call of a new signature exports the traced
program (``jax.export``: serialized StableHLO) to a file named by a key, and a later
process with the same key deserializes it and calls it, which costs the lowering of a
call to it and a persistent-cache lookup, not the trace.

The key (:func:`signature`) is a SHA-256 of

- the function (module and qualified name) and its compiler options;
- every static input: the structure of the arguments (equinox modules' static fields,
  such as the model's terms, included) and the value of every non-array leaf;
- the shape, dtype and weak type of every array leaf;
- the fricjax source (every ``.py`` file of the package), the versions of jax, jaxlib and
  the libraries whose code is traced into the programs (equinox, optimistix, lineax,
  numpy, scipy), the platform and the ``jax_enable_x64`` flag.

A static value whose text is not reproducible across processes (a lambda, a closure, an
object printed with its memory address) makes the call unstorable: it runs through
``equinox.filter_jit`` as before, so a stale program can never be loaded, only a missed
one recomputed. An unreadable or unwritable store degrades the same way.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import inspect
import os
import pickle
from collections.abc import Callable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any, Generic, ParamSpec, TypeVar

import equinox as eqx
import jax
import numpy as np

from fricjax.io.atomic import write_bytes_atomic

P = ParamSpec("P")
R = TypeVar("R")

#: Where exported programs live; None: nothing is stored (every call traces, as jit does).
_STORE: Path | None = None


def set_store(folder: str | Path | None) -> Path | None:
    """Store exported programs in ``folder`` (created), or nothing when None; returns the
    folder in use (None when it cannot be created)."""
    global _STORE
    if folder is None:
        _STORE = None
        return None
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        path = None
    _STORE = path
    return path


# whose code ends up in the traced programs (or computes constants folded into them)
_TRACED_LIBRARIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "scipy")


@functools.cache
def _environment() -> str:
    """The fricjax source, the traced libraries' versions and jax's settings: a program
    traced under any other is not reused."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    versions = []
    for package in _TRACED_LIBRARIES:
        try:
            versions.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{package} absent")
    return "|".join(
        (
            digest.hexdigest(),
            *versions,
            jax.default_backend(),
            str(jax.config.read("jax_enable_x64")),
        )
    )


class _Unstorable(Exception):
    """A static input whose text could differ in another process."""


def _text(obj: Any) -> str:
    """A text of a static value that is the same in every process and names everything a
    trace can read from it, or :class:`_Unstorable`. Only values whose content is known
    are accepted (no ``repr``: a custom one may leave out what the trace depends on)."""
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        return f"{type(obj).__name__}:{obj!r}"
    if isinstance(obj, enum.Enum):
        return f"{_qualified(type(obj))}.{obj.name}"
    if isinstance(obj, (np.ndarray, np.generic)):
        arr = np.asarray(obj)
        return f"ndarray({arr.dtype},{arr.shape},{hashlib.sha256(arr.tobytes()).hexdigest()})"
    if isinstance(obj, np.dtype):
        return f"dtype:{obj}"
    if isinstance(obj, type):
        return f"type:{_qualified(obj)}"
    if isinstance(obj, functools.partial):
        return f"partial({_text(obj.func)},{_text(obj.args)},{_text(obj.keywords)})"
    if inspect.isfunction(obj):
        if obj.__closure__ or "<" in obj.__qualname__:  # a closure, lambda or local function
            raise _Unstorable
        return f"function:{_qualified(obj)}"
    if isinstance(obj, (tuple, list)):
        fields = getattr(obj, "_fields", None)
        head = _qualified(type(obj)) if fields is not None else type(obj).__name__
        return f"{head}({','.join(_text(item) for item in obj)})"
    if isinstance(obj, dict) and type(obj) is dict:
        items = sorted((_text(k), _text(v)) for k, v in obj.items())
        return "{" + ",".join(f"{k}:{v}" for k, v in items) + "}"
    if dataclasses.is_dataclass(obj):  # equinox modules included
        fields = (f"{f.name}={_text(getattr(obj, f.name))}" for f in dataclasses.fields(obj))
        return f"{_qualified(type(obj))}({','.join(fields)})"
    raise _Unstorable


def _qualified(obj: Any) -> str:
    return f"{obj.__module__}.{obj.__qualname__}"


def signature(fn: Callable[..., Any], options: Mapping[str, Any] | None, args: Any) -> str | None:
    """The store key of ``fn(*args)`` (module docstring), or None when a static input
    has no reproducible text."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    try:
        parts = [_text(fn), _text(dict(options or {})), _text(static)]
    except _Unstorable:
        return None
    parts += [
        f"{a.shape}{a.dtype}{getattr(a, 'weak_type', False)}" for a in jax.tree.leaves(dynamic)
    ]
    parts.append(_environment())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _leaves(args: Any) -> list[Any]:
    return jax.tree.leaves(eqx.filter(args, eqx.is_array))


def _traced(args: Any) -> bool:
    """Called inside another trace (an exported program has no JVP, and the outer program
    is the one to store)."""
    return any(isinstance(a, jax.core.Tracer) for a in jax.tree.leaves(args))


class _Program:
    """A deserialized (or just exported) program: flat arrays in, the output rebuilt."""

    def __init__(
        self, name: str, exported: jax.export.Exported, outputs: tuple[Any, Any], options: Any
    ):
        def call(*leaves: Any) -> Any:
            return exported.call(*leaves)

        # named for the function, so that jax's compile events and profiles tell them apart
        call.__name__ = call.__qualname__ = name
        self.call = jax.jit(call, compiler_options=options)
        self.structure, self.static = outputs

    def __call__(self, leaves: list[Any]) -> Any:
        return self.rebuild(self.call(*leaves))

    def rebuild(self, out_leaves: list[Any]) -> Any:
        return eqx.combine(jax.tree.unflatten(self.structure, out_leaves), self.static)


class Stored(Generic[P, R]):
    """``fn`` compiled like ``equinox.filter_jit(fn, compiler_options=options)``, its
    traced programs kept in the store (:func:`stored`)."""

    def __init__(self, fn: Callable[P, R], options: dict[str, Any] | None = None):
        self.fn = fn
        self.options = options
        self.jit = eqx.filter_jit(fn, compiler_options=options)
        self.loaded: dict[str, _Program | None] = {}  # None: jax cannot export it
        functools.update_wrapper(self, fn)

    def __call__(self, *args: P.args, **kwargs: P.kwargs) -> R:
        program = self._program(args, kwargs)
        if program is None:
            return self.jit(*args, **kwargs)
        out: R = program(_leaves((args, kwargs)))
        return out

    def compiled(self, *args: P.args, **kwargs: P.kwargs) -> Callable[P, R]:
        """The program for these arguments, compiled now (so that a caller can time the
        compilation apart from the run); call it with arguments of the same signature."""
        program = self._program(args, kwargs)
        if program is None:
            ready: Callable[P, R] = self.jit.lower(*args, **kwargs).compile()
            return ready
        executable = program.call.lower(*_leaves((args, kwargs))).compile()

        def run(*args: P.args, **kwargs: P.kwargs) -> R:
            out: R = program.rebuild(executable(*_leaves((args, kwargs))))
            return out

        return run

    def _program(self, args: Any, kwargs: Any) -> _Program | None:
        """The stored program of this signature (loaded or exported now), or None when
        no store is set or the call cannot be stored."""
        folder = _STORE
        if folder is None or _traced((args, kwargs)):
            return None
        key = signature(self.fn, self.options, (args, kwargs))
        if key is None:
            return None
        if key in self.loaded:
            return self.loaded[key]
        path = folder / f"{key}.jaxexport"
        program = self._load(path) or self._export(path, args, kwargs)
        self.loaded[key] = program
        return program

    def _load(self, path: Path) -> _Program | None:
        try:
            blob = path.read_bytes()
            outputs, serialized = pickle.loads(blob)
            exported = jax.export.deserialize(serialized)
        except Exception:  # absent, truncated or from an incompatible jax: trace instead
            return None
        return _Program(self.fn.__name__, exported, outputs, self.options)

    def _export(self, path: Path, args: Any, kwargs: Any) -> _Program | None:
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, structure = jax.tree.flatten(dynamic)
        outputs: list[tuple[Any, Any]] = []

        def flat(*arrays: Any) -> list[Any]:
            a, k = eqx.combine(jax.tree.unflatten(structure, arrays), static)
            out_dynamic, out_static = eqx.partition(self.fn(*a, **k), eqx.is_array)
            out_leaves, out_structure = jax.tree.flatten(out_dynamic)
            outputs.append((out_structure, out_static))
            return out_leaves

        flat.__name__ = flat.__qualname__ = self.fn.__name__

        specs = [
            jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=getattr(a, "weak_type", False))
            for a in leaves
        ]
        # The key pins the jaxlib that wrote the program, so the custom calls it makes (LAPACK's
        # QR of the LM solve) need no compatibility across versions: allow them all.
        everything = jax.export.DisabledSafetyCheck.custom_call("ALL")
        try:
            exported = jax.export.export(jax.jit(flat), disabled_checks=[everything])(*specs)
        except Exception:  # a program jax cannot export (a host callback): jit it as before
            return None
        try:
            blob = pickle.dumps((outputs[0], exported.serialize()))
            write_bytes_atomic(path, blob)
        except Exception:  # an output that does not pickle, a full disk: keep it in memory
            pass
        return _Program(self.fn.__name__, exported, outputs[0], self.options)


def stored(fn: Callable[P, R], *, compiler_options: dict[str, Any] | None = None) -> Stored[P, R]:
    """``fn`` jitted as ``equinox.filter_jit`` does, its programs stored on disk while a
    store is set (module docstring). Use it for programs whose trace costs seconds."""
    return Stored(fn, compiler_options)


def enable_compilation_cache(path: str | Path | None = None) -> Path | None:
    """Keep compiled XLA executables on disk across processes (jax's persistent cache).

    Compilation, not computation, dominates a cold ``fricjax identify`` (the
    Levenberg-Marquardt polish alone compiles for several seconds); later processes load
    the executables instead. Directory: ``path``, else ``$FRICJAX_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/fricjax/jax`` (``~/.cache/fricjax/jax``); a few MB per recording and
    config (jax evicts nothing; delete the folder to reclaim it).
    ``FRICJAX_COMPILATION_CACHE=0`` turns it off. The cache
    key is the compiled program itself (data embedded as constants included) plus the jax,
    XLA and platform versions, so a stale entry cannot be used; an unwritable directory
    only disables the cache. Its ``programs/`` folder keeps the traced programs as well
    (:mod:`fricjax.programs`, keyed on the fricjax source, the model structure, the
    settings and the shapes), so that a later process skips tracing too: most of a warm
    ``fricjax diagnose`` otherwise. Returns the directory, or None when off.
    """
    if os.environ.get("FRICJAX_COMPILATION_CACHE", "1") == "0":
        return None
    import jax

    default = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fricjax" / "jax"
    where_to = Path(path or os.environ.get("FRICJAX_CACHE_DIR") or default)
    try:
        where_to.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(where_to))
    # every program of a run is worth keeping: the small ones add up too
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    set_store(where_to / "programs")
    return where_to
