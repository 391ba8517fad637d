"""Compiled programs kept between processes (docs/numerics.md, "Compilation"): JAX's
persistent compilation cache in a per-user folder, so that the second run of the same
program loads it from disk instead of compiling it again, and jaxtissue's saved
executables (`saved_executables`, `call`), with which a second run of `simulate` skips
tracing and lowering as well. The command line enables both; Python users may call
`enable_compilation_cache()` and use `saved_executables` themselves.

The folder is `$XDG_CACHE_HOME/jaxtissue` (default `~/.cache/jaxtissue`);
`JAXTISSUE_NO_CACHE=1` turns it off; a folder set for JAX itself
(`JAX_COMPILATION_CACHE_DIR`) is used as it is. A folder that cannot be made or written costs a
warning, never a failure, and so does an unreadable entry (JAX recompiles). Programs
with host callbacks (progress bars fed from inside a run) are never cached.

`use_fast_compilation()` (also the command line's) has XLA compile CPU programs with
its classic fusion emitter, which for jaxtissue's programs compiles ~30–40 % faster with
the same run time and results equal to round-off; `JAXTISSUE_XLA_DEFAULTS=1` keeps XLA's
defaults. `collect_less()` (the command line's too) keeps Python's cycle collector from
rescanning the imported libraries while JAX traces.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import enum
import functools
import hashlib
import os
import pathlib
import re
import tempfile
import threading
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

MAX_SIZE_BYTES = 2 * 1024**3
"""The folder's size limit; least recently used entries go first."""


FAST_COMPILATION_FLAG = "--xla_cpu_use_fusion_emitters=false"
"""The XLA setting of `use_fast_compilation`."""


def use_fast_compilation() -> bool:
    """Add `FAST_COMPILATION_FLAG` to `XLA_FLAGS` (docs/numerics.md, "Compilation"), as
    `add_xla_flag` does, only where this jaxlib has the flag (XLA aborts on a flag it
    does not know) and not with `JAXTISSUE_XLA_DEFAULTS` set to anything but "" or "0".
    Returns whether the setting was made."""
    if os.environ.get("JAXTISSUE_XLA_DEFAULTS", "") not in ("", "0"):
        return False
    return _jaxlib_knows(_flag_name(FAST_COMPILATION_FLAG).encode()) and add_xla_flag(FAST_COMPILATION_FLAG)


def add_xla_flag(flag: str) -> bool:
    """Append `flag` ("--name=value") to `XLA_FLAGS`: only before JAX starts its backends
    (XLA reads the flags then) and never over a value of `name` already there. Returns
    whether the flag was added."""
    try:  # not public API: where it is missing, leave XLA as it is
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if _flag_name(flag) in flags or backends_are_initialized():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()
    return True


def _flag_name(flag: str) -> str:
    return flag.removeprefix("--").split("=")[0]


def _jaxlib_knows(flag: bytes) -> bool:
    """Whether the name of an XLA flag is in jaxlib's libraries (where XLA's flags are)."""
    import mmap

    import jaxlib

    for library in sorted(pathlib.Path(jaxlib.__file__).parent.glob("*.so"), key=lambda p: -p.stat().st_size):
        try:
            with open(library, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                if m.find(flag) >= 0:
                    return True
        except (OSError, ValueError):
            continue
    return False


def collect_less() -> None:
    """Python's cycle collector set for tracing (docs/numerics.md, "Compilation"): the
    objects made so far (the libraries imported) frozen, never scanned again, and a
    collection every 50 000 new objects instead of 700. JAX's tracing makes many
    short-lived objects, and with Python's defaults the collector rescans every
    imported library's objects again and again. A setting of the process, for a
    program's entry point after its imports, not for a library."""
    import gc

    gc.freeze()
    gc.set_threshold(50_000, 10, 10)


def default_folder() -> pathlib.Path | None:
    """`$XDG_CACHE_HOME/jaxtissue` (default `~/.cache/jaxtissue`, also where
    `XDG_CACHE_HOME` is relative, which the XDG specification calls invalid), or None if
    `JAXTISSUE_NO_CACHE` is set to anything but "" or "0"."""
    if os.environ.get("JAXTISSUE_NO_CACHE", "") not in ("", "0"):
        return None
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "jaxtissue"


def _writable(folder: pathlib.Path) -> str | None:
    """None if `folder` exists (or was made) and takes a file, else why not."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as err:
        return err.strerror or type(err).__name__
    return None


def enable_compilation_cache(folder: str | os.PathLike | None = None) -> pathlib.Path | None:
    """Use JAX's persistent compilation cache in `folder` (default: `default_folder()`).

    Returns the folder in use, or None if the cache stays off (turned off, or the
    folder is not writable: then with a warning). Without `folder`, a cache folder
    already set for JAX (`JAX_COMPILATION_CACHE_DIR`) is kept. Call it before the
    first compilation: JAX fixes the folder when it first compiles."""
    if folder is None and jax.config.jax_compilation_cache_dir:  # the user's own (JAX_COMPILATION_CACHE_DIR)
        return pathlib.Path(jax.config.jax_compilation_cache_dir)
    path = default_folder() if folder is None else pathlib.Path(folder)
    if path is None:
        return None
    problem = _writable(path)
    if problem is not None:
        warnings.warn(f"compilation cache folder {path} is not usable ({problem}); compiling without it "
                      "(set XDG_CACHE_HOME, or JAXTISSUE_NO_CACHE=1 to silence this)", RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_SIZE_BYTES)
    return path


# ---------------------------------------------------------------------------------------
# Saved executables: a second run skips tracing and lowering as well
# ---------------------------------------------------------------------------------------

MAX_EXECUTABLES = 64
"""Saved executables kept in their folder; least recently used go first."""

_FORMAT = 3
_SUFFIX = ".jtx"
_folder: contextvars.ContextVar[pathlib.Path | None] = contextvars.ContextVar("jaxtissue_saved_programs", default=None)
"""`saved_executables`' folder, per thread (a new thread starts without one unless run
in a copy of its starter's context): tasks in several threads of one process, as in a
Dask worker, each keep their own."""
_loaded: dict = {}  # key -> _Entry, this process's programs


class _Out:
    """Marks where an output array goes in a saved result's skeleton."""


_OUT = _Out()


@contextlib.contextmanager
def saved_executables(folder: str | os.PathLike | None):
    """Within the block, in this thread, `call` keeps the compiled programs it runs as
    files in `folder` (None, or `JAXTISSUE_NO_SAVED_PROGRAMS` set to anything but "" or
    "0": off), and a later process loads them instead of tracing, lowering and compiling
    again (docs/numerics.md, "Compilation"). The command line's runs use
    `<cache folder>/executables`."""
    if os.environ.get("JAXTISSUE_NO_SAVED_PROGRAMS", "") not in ("", "0"):
        folder = None
    token = _folder.set(None if folder is None else pathlib.Path(folder))
    try:
        yield
    finally:
        _folder.reset(token)


def saved_folder() -> pathlib.Path | None:
    """The folder that `saved_executables` keeps programs in here and now (None: off):
    what a sweep's Dask workers are given to keep theirs in (`sweep_dask.run`)."""
    return _folder.get()


def call(jitted, *args):
    """`jitted(*args)`, for an `eqx.filter_jit` function (array leaves traced, the rest
    static), through a saved executable where `saved_executables` is on and no argument
    is traced: looked up by a key of the function, its static arguments, the shapes and
    dtypes of its arrays, jaxtissue's source and the versions, flags and devices that
    compile it. A program that cannot be saved (one with host callbacks: a progress bar)
    runs from memory; an unreadable file costs a warning and a compilation."""
    found = _program(jitted, args)
    if found is None:
        return jitted(*args)
    entry, leaves = found
    return entry(leaves)


def prepared(jitted, *args):
    """`jitted`'s program for arguments like `args` (the same static values, array
    shapes and dtypes), loaded or compiled now (as `call` would) and returned as a
    function of such arguments: compilation timed apart from the runs."""
    found = _program(jitted, args)
    if found is None:
        return jitted.lower(*args).compile()
    entry, _ = found
    return lambda *a: entry(jtu.tree_leaves(eqx.filter(a, eqx.is_array)))


def _program(jitted, args):
    """(`_Entry`, the arrays of `args`) of `call`'s saved or newly compiled program, or
    None where none is saved (off, traced arguments, no key)."""
    folder, fn = _folder.get(), getattr(jitted, "__wrapped__", None)
    if folder is None or fn is None:  # off, or not a jitted function
        return None
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jtu.tree_flatten(dynamic)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return None
    key = _key(fn, treedef, static, leaves)
    if key is None:  # a static argument without a stable description (e.g. a function)
        return None
    entry = _loaded.get(key) or _load(folder / f"{key}{_SUFFIX}")
    if entry is None:
        entry = _compile(fn, treedef, static, leaves, key)
        _save(folder, key, entry, len(leaves))
    _loaded.pop(key, None)
    _loaded[key] = entry  # the most recent last; a few kept
    while len(_loaded) > 8:
        del _loaded[next(iter(_loaded))]
    return entry, leaves


class _Entry:
    """A compiled program taking and giving flat lists of arrays, and `skeleton`: its
    result with `_Out` where the arrays go (what `_save` pickles)."""

    def __init__(self, compiled, skeleton, callbacks: bool = False, lapack: bool = False):
        self.compiled, self.skeleton, self.callbacks, self.lapack = compiled, skeleton, callbacks, lapack
        self.parts, self.structure = _flatten(skeleton)

    def __call__(self, leaves):
        placed = jax.device_put(tuple(leaves), self.compiled.input_shardings[0])  # as `jit` places them (e.g. split over devices)
        outputs = iter(self.compiled(*placed))
        return jtu.tree_unflatten(self.structure, [next(outputs) if x is _OUT else x for x in self.parts])


def _flatten(skeleton) -> tuple[list, jtu.PyTreeDef]:
    """A skeleton's leaves, with `_OUT` where the arrays go (one marker, also after
    unpickling), and its structure."""
    parts, structure = jtu.tree_flatten(skeleton, is_leaf=lambda x: isinstance(x, _Out))
    return [_OUT if isinstance(x, _Out) else x for x in parts], structure


def _compile(fn, treedef, static, leaves, key: str) -> _Entry:
    """Trace, lower and compile `fn` as a program of flat arrays, named after it and `key`
    (`<name>_<key>`: a program of its own in JAX's cache too)."""
    box = {}

    def flat(*leaves):
        out = fn(*eqx.combine(jtu.tree_unflatten(treedef, leaves), static))
        arrays, rest = eqx.partition(out, eqx.is_array)
        box["skeleton"] = eqx.combine(jtu.tree_map(lambda _: _OUT, arrays), rest)
        return jtu.tree_leaves(arrays)

    def compiled_as(name):
        flat.__name__ = flat.__qualname__ = name
        before = _cache_hits()
        lowered = jax.jit(flat).lower(*leaves)
        return lowered, lowered.compile(), _cache_hits() > before

    name = f"{fn.__name__}_{key[:12]}"
    lowered, compiled, from_jax_cache = compiled_as(name)
    if from_jax_cache:
        # on the CPU an executable that JAX loaded from its cache serialises without its
        # kernels ("Function ... not found" in the next process): compile it afresh
        import secrets

        lowered, compiled, _ = compiled_as(f"{name}_{secrets.token_hex(4)}")
    text = lowered.as_text()
    return _Entry(compiled, box["skeleton"], _HOST_CALLBACK.search(text) is not None, _LAPACK.search(text) is not None)


_HOST_CALLBACK = re.compile(r"custom_call @\w*python\w*callback")
"""How a host callback (`jax.debug.callback`, `jax.pure_callback`) appears in a lowered
program: a call into this Python process, which a saved program cannot make."""

_LAPACK = re.compile(r"custom_call @lapack_")
"""How a call into jaxlib's LAPACK kernels appears in a lowered program (e.g. the
least-squares solve of `numerics.LevenbergMarquardt`)."""


@functools.cache
def _ready_lapack() -> None:
    """Make jaxlib's LAPACK kernels callable: JAX does so when it lowers a program that
    calls them, and a loaded program is never lowered (it would crash in its first
    LAPACK call). One small program lowered, never compiled."""
    jax.jit(jnp.linalg.cholesky).lower(jax.ShapeDtypeStruct((1, 1), jnp.float64))


_hits = threading.local()


def _cache_hits() -> int:
    """JAX's persistent-cache hits in this thread so far (`jax.monitoring`)."""
    _listen()
    return getattr(_hits, "n", 0)


@functools.cache
def _listen() -> None:
    """Count `_cache_hits` from now on (once per process)."""
    def count(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            _hits.n = getattr(_hits, "n", 0) + 1

    jax.monitoring.register_event_listener(count)


def _save(folder: pathlib.Path, key: str, entry: _Entry, n_in: int) -> None:
    """Write `entry` atomically as `<key>.jtx`, unless its program cannot be serialised."""
    import pickle

    from jax.experimental.serialize_executable import serialize

    from .io import atomic_write

    if entry.callbacks:
        return  # its callbacks live in this process only
    try:
        blob, _, _ = serialize(entry.compiled)
        devices = sorted({d.id for s in jtu.tree_leaves(entry.compiled.input_shardings) for d in s.device_set})
        data = pickle.dumps((_FORMAT, blob, n_in, devices, entry.skeleton, entry.lapack))
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write(folder / f"{key}{_SUFFIX}", lambda f: f.write(data))
        _prune(folder)
    except Exception as err:  # a cache that cannot be written costs a warning, never the run
        warnings.warn(f"could not save a compiled program in {folder} ({type(err).__name__}: {err}); "
                      "the next run compiles it again", RuntimeWarning, stacklevel=4)


def _prune(folder: pathlib.Path) -> None:
    """Keep the `MAX_EXECUTABLES` most recently used files (another process may be
    pruning too)."""
    def last_used(path):
        try:
            return path.stat().st_mtime
        except OSError:
            return 0.0

    for path in sorted(folder.glob(f"*{_SUFFIX}"), key=last_used, reverse=True)[MAX_EXECUTABLES:]:
        path.unlink(missing_ok=True)


def _load(path: pathlib.Path) -> _Entry | None:
    """The saved executable at `path`, or None (absent; unreadable: with a warning)."""
    import pickle

    from jax.experimental.serialize_executable import deserialize_and_load

    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        saved = pickle.loads(data)
        if saved[0] != _FORMAT:  # another format: compiled afresh
            return None
        _, blob, n_in, device_ids, skeleton, lapack = saved
        if lapack:
            _ready_lapack()
        n_out = _flatten(skeleton)[0].count(_OUT)
        devices = {d.id: d for d in jax.devices()}
        compiled = deserialize_and_load(blob, jtu.tree_structure((tuple(range(n_in)), {})), jtu.tree_structure(list(range(n_out))),
                                        execution_devices=[devices[i] for i in device_ids])
        os.utime(path)  # recently used
        return _Entry(compiled, skeleton, lapack=lapack)
    except Exception as err:
        warnings.warn(f"saved program {path} is unreadable ({type(err).__name__}); compiling it again", RuntimeWarning, stacklevel=4)
        return None


_UNDESCRIBED = re.compile(r" at 0x[0-9a-f]+|\b(?:weak_)?(?:bool|bf16|[fiuc]\d+)\[|\b(?:array|Array)\(")
"""Where a static argument's repr does not say what it holds: an address (a function,
say: its program would never be found again), or an array inside it (equinox prints
`f64[3]`, NumPy rounds and elides), whose values a program may hold as constants."""


def _key(fn, treedef, static, leaves) -> str | None:
    """A hex digest of `_description`, or None where a static argument cannot be fully
    described (`_describe`)."""
    try:
        text = _description(fn, treedef, static, leaves)
    except (_Undescribed, RecursionError):
        return None
    return None if _UNDESCRIBED.search(text) else hashlib.sha256(text.encode()).hexdigest()[:40]


def _description(fn, treedef, static, leaves) -> str:
    """What names the program of `fn` for these arguments: the environment
    (`_environment`), the function, the structure and static values of its arguments
    and the shape and dtype of each array."""
    return "\n".join([
        _environment(), f"{fn.__module__}.{fn.__qualname__}", repr(treedef), _describe(static),
        *(f"{jnp.shape(x)} {jnp.result_type(x)} {getattr(x, 'weak_type', False)}" for x in leaves),
    ])


class _Undescribed(Exception):
    """A static value that `_describe` cannot name exactly."""


def _describe(x) -> str:
    """An exact description of a static value: every field of a dataclass (an equinox
    module's static fields included, and fields its repr leaves out), the items of
    tuples, lists and dicts, arrays by dtype, shape and a digest of their bytes, numbers
    and strings by their (round-tripping) repr; any other object by its repr, which
    must not hide what it holds (`_UNDESCRIBED`; else `_Undescribed`)."""
    kind = f"{type(x).__module__}.{type(x).__qualname__}"
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes, enum.Enum)):
        return f"{kind} {x!r}"
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        if isinstance(x, jax.core.Tracer):
            raise _Undescribed(kind)
        a = np.ascontiguousarray(x)
        return f"{kind} {a.dtype} {a.shape} {hashlib.sha256(a.tobytes()).hexdigest()}"
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return f"{kind}(" + ", ".join(f"{f.name}={_describe(getattr(x, f.name))}" for f in dataclasses.fields(x)) + ")"
    if isinstance(x, (tuple, list)):
        return f"{kind}[" + ", ".join(map(_describe, x)) + "]"
    if isinstance(x, dict):
        return f"{kind}{{" + ", ".join(sorted(f"{_describe(k)}: {_describe(v)}" for k, v in x.items())) + "}"
    if isinstance(x, (set, frozenset)):
        return f"{kind}{{" + ", ".join(sorted(map(_describe, x))) + "}"
    text = repr(x)
    if _UNDESCRIBED.search(text):
        raise _Undescribed(text)
    return f"{kind} {text}"


@functools.lru_cache(maxsize=1)
def _environment() -> str:
    """What else decides a compiled program: jaxtissue's source, the versions of the
    libraries that trace and compile it, XLA's flags and the devices."""
    import importlib.metadata

    source = hashlib.sha256()
    package = pathlib.Path(__file__).resolve().parent
    for path in sorted(package.rglob("*.py")):
        source.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    versions = []
    for name in ("jax", "jaxlib", "equinox", "diffrax", "lineax", "optimistix", "numpy"):
        try:
            versions.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{name}=?")
    devices = jax.devices()
    return "\n".join([
        source.hexdigest(), " ".join(versions), os.environ.get("XLA_FLAGS", ""), os.environ.get("EQX_ON_ERROR", ""),
        f"x64={jax.config.jax_enable_x64}", f"{devices[0].platform} {devices[0].client.platform_version} {len(devices)} "
        + " ".join(sorted({d.device_kind for d in devices})),
    ])
