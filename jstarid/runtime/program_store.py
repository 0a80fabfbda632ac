"""Compiled programs kept on disk, so that a later process skips tracing, lowering and compiling.

JAX's persistent compilation cache (:func:`jstarid.enable_compilation_cache`) keeps XLA
executables, but finds one only after the function was traced and lowered again: the key is the
lowered module. SGM compiles hundreds of small programs (kernel × graph-size bucket × call size),
and in a warm ``jstarid demo`` tracing and lowering them took most of the run (≈ 30 s of tracing and
12 s of lowering against 7 s of loading the executables, ``JAX_LOG_COMPILES=1``; experiments/
RESULTS.md, "Warm runs: programs kept on disk"). The store keys a program by what the call site
knows before tracing — the function's qualified name, its static arguments, the shapes, dtypes and
shardings of its array arguments — salted with everything else the program depends on: the source
of the jstarid package (a hash of every module), the JAX and jaxlib versions, the devices, the
``XLA_FLAGS`` and the JAX settings that change numerics. A hit loads the serialized executable
(``jax.experimental.serialize_executable``, a few ms) and calls it directly.

The store is off unless :func:`enable_program_store` turned it on (the CLI and the experiment
scripts do, through :func:`jstarid.enable_compilation_cache`; the library alone writes nothing);
then, and only then, :func:`stored_jit` functions look programs up there. A call inside a trace,
with several processes (``jax.distributed``) or with a static argument whose ``repr`` is not stable
across processes runs the plain ``jax.jit`` path. A file that cannot be read is compiled again and
rewritten; a program that cannot be serialized (host callbacks) stays in memory only. The files
are pickled executables, run when loaded: like JAX's own cache, the directory must be writable by
its user alone (the default is under ``~/.cache/jstarid``).

:func:`set_compiler_options` gives chosen programs their own XLA options while the store is on (a
test suite that builds most programs at a low optimisation level, for speed of compilation, builds
its loop-bound kernels at a higher one); the options are part of each program's key.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import logging
import os
import pickle
import shutil
import sys
import tempfile
import types
import weakref
from collections.abc import Callable, Mapping
from pathlib import Path

import jax

__all__ = ["StoredFunction", "disable_program_store", "enable_program_store", "forget_programs",
           "program_store_dir", "program_store_stats", "programs_stored", "set_compiler_options",
           "storable_name", "stored", "stored_jit"]

_log = logging.getLogger(__name__)
_SUFFIX = ".jaxprog"
KEEP_VERSIONS = 3  # salt directories kept (jstarid sources × JAX versions × device setups)
_state = types.SimpleNamespace(dir=None, salt=None, folder=None, loaded=0, compiled=0, written=0,
                               options=None)
_functions: weakref.WeakSet = weakref.WeakSet()
_xla_cache_hits = [0]


def _on_event(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _xla_cache_hits[0] += 1


jax.monitoring.register_event_listener(_on_event)


def enable_program_store(path: str | os.PathLike) -> Path:
    """Turn the program store on in this process, under ``path`` (created if missing).

    Args:
        path: directory for the stored programs (``<jstarid cache>/programs`` from the CLI).

    Returns:
        The directory.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    _state.dir, _state.salt, _state.folder = path, None, None
    return path


def disable_program_store() -> None:
    """Turn the store off (later calls use ``jax.jit``; programs already loaded stay usable)."""
    _state.dir, _state.salt, _state.folder = None, None, None


def program_store_dir() -> Path | None:
    """The store's directory, or None while it is off."""
    return _state.dir


def program_store_stats() -> dict:
    """Counts since the process started: programs ``loaded`` from disk, ``compiled`` here (store on)
    and ``written`` to disk."""
    return {"loaded": _state.loaded, "compiled": _state.compiled, "written": _state.written}


def programs_stored() -> int:
    """Programs on disk for this process's sources, JAX and devices (0 while the store is off)."""
    if _state.dir is None or _salt() is None:
        return 0
    return sum(1 for _ in _folder().glob(f"*{_SUFFIX}"))


def set_compiler_options(options: Callable[[str], Mapping[str, object] | None] | None
                         ) -> Callable[[str], Mapping[str, object] | None] | None:
    """XLA options for the programs the store compiles from now on, chosen by program name.

    Args:
        options: called with a stored function's name (``module.qualname`` plus its closure's
            settings, see :class:`StoredFunction`); returns ``jax.stages.Lowered.compile``'s
            ``compiler_options`` (XLA flag names without ``--``, e.g.
            ``{"xla_backend_optimization_level": 2}``) or None for the process's ``XLA_FLAGS`` alone.
            None: every program under ``XLA_FLAGS`` alone (the default).

    Returns:
        The setting it replaces (to restore it).

    Programs already in memory keep their options; :func:`forget_programs` drops them. Only calls
    that go through the store (it is on, the call is not inside a trace) see the options.
    """
    previous, _state.options = _state.options, options
    return previous


def _compiler_options(name: str) -> dict | None:
    chosen = None if _state.options is None else _state.options(name)
    return dict(chosen) if chosen else None


def forget_programs() -> None:
    """Drop the programs every stored function holds in memory (like ``jax.clear_caches`` for
    jit's; the files stay, so a later call loads them again)."""
    for f in list(_functions):
        f._programs.clear()


@functools.cache
def _source_hash() -> str:
    """SHA-256 of every module of the installed jstarid package (paths and contents)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def _salt() -> str | None:
    """Everything a program depends on beyond its call site (None: do not store, with several
    processes or where LAPACK cannot be readied)."""
    if _state.salt is None:
        import jaxlib

        if jax.process_count() > 1 or not _lapack_ready():
            _state.salt = ""
        else:
            devices = jax.local_devices()
            _state.salt = "\n".join([
                _source_hash(), jax.__version__, jaxlib.__version__, sys.version.split()[0],
                jax.default_backend(), f"{len(devices)} × {devices[0].device_kind}",
                os.environ.get("XLA_FLAGS", ""), str(jax.config.jax_enable_x64),
                str(jax.config.jax_default_matmul_precision)])
    return _state.salt or None


def _folder() -> Path:
    """This process's salt directory under the store (created, marked as used now); the least
    recently used beyond :data:`KEEP_VERSIONS` are deleted, so edits and upgrades do not pile up."""
    if _state.folder is None:
        folder = _state.dir / hashlib.sha256(_state.salt.encode()).hexdigest()[:16]
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)
        others = sorted((p for p in _state.dir.iterdir() if p.is_dir() and p != folder),
                        key=lambda p: p.stat().st_mtime, reverse=True)
        for old in others[KEEP_VERSIONS - 1:]:
            shutil.rmtree(old, ignore_errors=True)
        _state.folder = folder
    return _state.folder


class _Unstorable(Exception):
    """A call the store must leave to ``jax.jit`` (traced arguments, unstable static reprs)."""


@contextlib.contextmanager
def _xla_cache_bypassed():
    """Compile without JAX's persistent cache: an executable read back from it serializes without
    some of its functions on XLA:CPU (jaxlib 0.10: the reloaded program fails with "Function
    wrapped_slice.1 not found"), so the store compiles its programs afresh. JAX decides once per
    process whether its cache is in use and has no public switch for one compilation; where those
    private names moved, :meth:`StoredFunction._load_or_compile` still sees the cache hit and keeps
    that program in memory only."""
    try:
        from jax._src import compilation_cache as cc
        lock, saved = cc._cache_initialized_mutex, (cc._cache_checked, cc._cache_used)
    except (ImportError, AttributeError):
        yield
        return
    with lock:
        cc._cache_checked, cc._cache_used = True, False
    try:
        yield
    finally:
        with lock:
            cc._cache_checked, cc._cache_used = saved


@functools.cache
def _lapack_ready() -> bool:
    """Load LAPACK's function table as lowering a linear-algebra op would. A program read back
    from the store was never lowered here, and its LAPACK calls (``eigh``, ``svd``) would jump
    through null pointers. False (store unusable) where that private hook moved."""
    try:
        from jax._src.lax import linalg
        linalg.initialize_lapack()
    except (ImportError, AttributeError) as err:
        _log.warning("program store off: cannot initialise LAPACK before loading programs (%s)", err)
        return False
    return True


def _leaf_key(x):
    if isinstance(x, jax.core.Tracer):
        raise _Unstorable
    if isinstance(x, jax.Array):
        aval = x.aval
        return aval.shape, aval.dtype, aval.weak_type, x.sharding if x.committed else None
    aval = jax.typeof(x)
    return aval.shape, aval.dtype, aval.weak_type, None


def _stable_repr(value) -> str:
    text = repr(value)
    if " at 0x" in text:  # an object's address: differs from process to process
        raise _Unstorable
    return text


class StoredFunction:
    """A ``jax.jit`` function whose compiled programs are kept in the program store.

    Called like the jitted function. While the store is off it *is* the jitted function (one
    attribute test more per call). While it is on, each call's key (static values, the arguments'
    tree, shapes, dtypes, weak types and committed shardings) finds its compiled program in memory,
    else on disk, else lowers and compiles it and writes it to the store.

    Args:
        jitted: the ``jax.jit`` function.
        name: a name unique to the program's source (module and qualified name, plus anything
            the jitted closure fixes, e.g. a kernel's static arguments and the mesh); None: never
            stored (see :func:`storable_name`).
        static_argnames: the arguments ``jitted`` treats as static.
        static_positions: ``{position: name}`` of those that may also be passed positionally.
    """

    def __init__(self, jitted, name: str, static_argnames=(), static_positions=None):
        self._jit = jitted
        self._name = name
        self._static = frozenset(static_argnames)
        self._positions = dict(static_positions or {})
        self._programs: dict = {}
        functools.update_wrapper(self, jitted)
        _functions.add(self)

    def __getattr__(self, name):  # the jitted function's other attributes (``_cache_size``, ``trace``)
        if name == "_jit":  # not yet set (copies, unpickling)
            raise AttributeError(name)
        return getattr(self._jit, name)

    def _cache_size(self) -> int:
        """Programs this function holds in memory: the jitted function's and the store's (as
        ``jax.jit``'s ``_cache_size``: a test that counts compilations counts both paths)."""
        return self._jit._cache_size() + len(self._programs)

    def lower(self, *args, **kwargs):
        """``jitted.lower`` (ahead-of-time use, never stored)."""
        return self._jit.lower(*args, **kwargs)

    def __call__(self, *args, **kwargs):
        # under jax.disable_jit() the jitted function runs op by op; a stored program cannot
        if _state.dir is None or self._name is None or jax.config.jax_disable_jit:
            return self._jit(*args, **kwargs)
        static = {k: v for k, v in kwargs.items() if k in self._static}
        dynamic = {k: v for k, v in kwargs.items() if k not in self._static}
        if self._positions and any(i < len(args) for i in self._positions):
            static.update((n, args[i]) for i, n in self._positions.items() if i < len(args))
            dyn_args = tuple(a for i, a in enumerate(args) if i not in self._positions)
        else:
            dyn_args = args
        try:
            leaves, tree = jax.tree.flatten((dyn_args, dynamic))
            key = (tuple(sorted(static.items())), tree, tuple(map(_leaf_key, leaves)))
            program = self._programs.get(key)
            if program is None:
                program = self._programs[key] = self._load_or_compile(key, args, kwargs)
        except _Unstorable:
            return self._jit(*args, **kwargs)
        return program(*dyn_args, **dynamic)

    def _file(self, key) -> tuple[Path, str] | None:
        salt = _salt()
        if salt is None:
            raise _Unstorable
        static, tree, leaves = key
        options = _compiler_options(self._name)
        text = "\n".join([salt, _stable_repr(self._name), _stable_repr(static), str(tree),
                          repr([(s, str(d), w, None if sh is None else repr(sh)) for s, d, w, sh in leaves]),
                          *([repr(sorted(options.items()))] if options else [])])
        digest = hashlib.sha256(text.encode()).hexdigest()[:40]
        return _folder() / f"{digest}{_SUFFIX}", text

    def _load_or_compile(self, key, args, kwargs):
        from jax.experimental import serialize_executable

        path, text = self._file(key)
        if path.exists():
            try:
                with open(path, "rb") as f:
                    stored_text, device_ids, payload, in_tree, out_tree = pickle.load(f)
                if stored_text == text:
                    # on the devices it was compiled for (by default JAX would load a one-device
                    # program onto every local device, and its call would then fail)
                    by_id = {d.id: d for d in jax.local_devices()}
                    program = serialize_executable.deserialize_and_load(
                        payload, in_tree, out_tree, execution_devices=[by_id[i] for i in device_ids])
                    _state.loaded += 1
                    return program
            except Exception as err:  # a damaged or foreign file: compile again and rewrite it
                _log.warning("program store: %s unreadable (%s); compiling again", path.name, err)
        hits = _xla_cache_hits[0]
        with _xla_cache_bypassed():
            program = self._jit.lower(*args, **kwargs).compile(
                compiler_options=_compiler_options(self._name))
        _state.compiled += 1
        if _xla_cache_hits[0] != hits:  # read back from JAX's cache: would not serialize whole
            return program
        try:
            device_ids = [d.id for d in program.runtime_executable().local_devices()]
            blob = pickle.dumps((text, device_ids, *serialize_executable.serialize(program)))
        except Exception as err:  # e.g. host callbacks: kept in memory only
            _log.info("program store: %s not serializable (%s)", self._name, err)
            return program
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the whole new one
        _state.written += 1
        return program


def storable_name(fn) -> str | None:
    """``module.qualname`` of a module-level function of jstarid, else None. Only jstarid's own
    source is in the salt: a user's kernel (``map_batch`` is public), a lambda or a closure could
    change without the key changing, and is never stored."""
    module, qualname = getattr(fn, "__module__", None), getattr(fn, "__qualname__", None)
    if not (isinstance(module, str) and isinstance(qualname, str)) or module.split(".")[0] != "jstarid":
        return None
    if "<" in qualname:  # <lambda>, <locals>
        return None
    return f"{module}.{qualname}"


def stored(jitted, name: str | None) -> StoredFunction:
    """Wrap an existing ``jax.jit`` function without static arguments (see :class:`StoredFunction`)."""
    return StoredFunction(jitted, name)


def stored_jit(fn=None, *, static_argnames=(), **jit_kwargs):
    """``jax.jit`` whose programs the program store keeps (a decorator, same arguments as ``jax.jit``
    with ``static_argnames``; static arguments may be passed by keyword or position).

    Example::

        @functools.partial(stored_jit, static_argnames=("camera",))
        def kernel(xy, *, camera): ...
    """
    if fn is None:
        return functools.partial(stored_jit, static_argnames=static_argnames, **jit_kwargs)
    static_argnames = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
    positional = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.POSITIONAL_ONLY)
    positions = {i: p.name for i, p in enumerate(inspect.signature(fn).parameters.values())
                 if p.name in static_argnames and p.kind in positional}
    jitted = jax.jit(fn, static_argnames=static_argnames, **jit_kwargs)
    return StoredFunction(jitted, storable_name(fn), static_argnames, positions)
