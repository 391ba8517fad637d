"""JAX's persistent compilation cache in a per-user folder (docs/numerics.md,
"Compilation"): the second run of the same program loads it from disk instead of
compiling it again. The command line enables it; Python users may call
`enable_compilation_cache()` themselves.

The folder is `$XDG_CACHE_HOME/jaxtissue` (default `~/.cache/jaxtissue`);
`JAXTISSUE_NO_CACHE=1` turns it off; a folder set for JAX itself
(`JAX_COMPILATION_CACHE_DIR`) is used as it is. A folder that cannot be made or written costs a
warning, never a failure, and so does an unreadable entry (JAX recompiles). Programs
with host callbacks (progress bars fed from inside a run) are never cached.

`use_fast_compilation()` (also the command line's) has XLA compile CPU programs with
its classic fusion emitter, which for jaxtissue's programs compiles ~30–40 % faster with
the same run time and results equal to round-off; `JAXTISSUE_XLA_DEFAULTS=1` keeps XLA's
defaults.
"""

from __future__ import annotations

import os
import pathlib
import tempfile
import warnings

import jax

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


def default_folder() -> pathlib.Path | None:
    """`$XDG_CACHE_HOME/jaxtissue` (default `~/.cache/jaxtissue`), or None if
    `JAXTISSUE_NO_CACHE` is set to anything but "" or "0"."""
    if os.environ.get("JAXTISSUE_NO_CACHE", "") not in ("", "0"):
        return None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
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
