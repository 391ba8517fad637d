"""Files: reading TOML input, parameter files, JSON summaries, NetCDF datasets, and
atomic output folders (results appear complete or not at all). `InputError` is the
one-line error of every mistake in a user's input."""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import pathlib
import shutil
import tempfile
import threading
import tomllib
import zipfile

import numpy as np

from .params import FIELDS, Params, suggest

class InputError(ValueError):
    """A user's input is wrong; the message is one line naming what and why."""


class RunError(RuntimeError):
    """A run that could not be carried out, through no fault of the input (e.g. a
    cluster that did not start): one line, exit code 1."""


_LOCKS: dict[pathlib.Path, int] = {}  # lock file -> its open descriptor, while this process writes there
_PARTIAL: set[pathlib.Path] = set()  # temporary output folders and files not yet renamed into place
_COMMIT = threading.Lock()  # renaming a finished folder into place, or discarding the partial ones
_ENDING: list[bool] = []  # set by `release_outputs(ending=True)`: the process is ending, no new partial output


def _new_partial(make):
    """`make()` a temporary file or folder (returns (its path, anything)) and register it
    as partial, unless the process is ending (then nothing is made: `RunError`)."""
    with _COMMIT:
        if _ENDING:
            raise RunError("interrupted")
        path, extra = make()
        _PARTIAL.add(pathlib.Path(path))
        return pathlib.Path(path), extra


def read_toml(path, kind: str, keys=None) -> tuple[dict, str]:
    """A TOML file's (table, text); a missing or malformed file, or a top-level key not
    in `keys`, is an `InputError` naming the file (`kind`: "sweep", "problem", ...)."""
    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (some editors write one) is not TOML
        doc = tomllib.loads(text)
    except FileNotFoundError:
        raise InputError(f"{path}: no such {kind} file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a {kind} file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a TOML {kind} file (not UTF-8 text)") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{path}: not valid TOML ({err})") from None
    for key in doc if keys is not None else ():
        if key not in keys:
            hint = suggest(key, sorted(keys))
            hint = hint if hint.startswith("did you mean") else f"allowed: {', '.join(sorted(keys))}"
            raise InputError(f"{path}: unknown key {key!r}; {hint}")
    return doc, text


def write_params_toml(params: Params, path, model: dict | None = None, notes: tuple[str, ...] = ()) -> None:
    """A TOML file loadable by `read_params_toml` (and `jaxtissue simulate --params`);
    `model`: a `[model]` table of the resolution the parameters were fitted at; `notes`:
    comment lines (e.g. why a value was chosen)."""
    lines = ["# jaxtissue model parameters (units: see `jaxtissue params`)", *(f"# {n}" for n in notes), "[parameters]"]
    for name, value in params.as_dict().items():
        lines.append(f"{name} = {value!r}  # {FIELDS[name].unit}")
    if model:
        lines += ["", "# The model resolution these values were fitted at; `jaxtissue simulate --params` uses it",
                  "# unless --grid is given.", "[model]"]
        lines += [f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v)}" for k, v in model.items()]
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_params_toml(path, base: Params | None = None) -> Params:
    """Parameters from a TOML file: a `[parameters]` table (or top-level keys) of
    `name = value`; names not given keep `base` (default: the paper's values)."""
    doc, _ = read_toml(path, "parameter")
    table = doc.get("parameters", doc)
    if not isinstance(table, dict):
        raise InputError(f"{path}: [parameters] must be a table of name = value")
    return params_from_table(table, str(path), base)


def number(value, where: str, positive: bool = False) -> float:
    """A finite (`positive`: and > 0) number from a TOML value, else an `InputError`
    naming `where`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{where} = {value!r} must be a {'positive' if positive else 'finite'} number")
    return float(value)


def params_from_table(table: dict, where: str, base: Params | None = None) -> Params:
    """Validated `Params` from a TOML table of `name = value` (names not given keep
    `base`); a mistake is an `InputError` starting with `where`."""
    changes = {}
    for name, value in table.items():
        if name not in FIELDS:
            raise InputError(f"{where}: unknown parameter {name!r}; {suggest(name, FIELDS)}")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: parameter {name} = {value!r} must be a number{FIELDS[name].unit_text}")
        changes[name] = float(value)
    return make_params(changes, base, where=where)


def make_params(changes: dict, base: Params | None = None, where: str = "parameters") -> Params:
    """Validated parameters; a bad value is an `InputError` naming where it came from."""
    base = Params() if base is None else base
    try:
        return base.replace(**changes)
    except (TypeError, ValueError) as err:  # a value out of range, or not a number
        raise InputError(f"{where}: {err}") from None


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    arr = np.asarray(value)
    if arr.dtype.kind in "fiub":
        return arr.tolist()
    return value


def write_json(path, data) -> None:
    atomic_write_text(path, json.dumps(_jsonable(data), indent=2) + "\n")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path, text: str) -> None:
    """Write via a temporary file in the same folder, then rename."""
    atomic_write(path, lambda f: f.write(text.encode()))


def read_arrays(path, keys, redo: str, length: int | None = None) -> dict:
    """The arrays of an .npz file jaxtissue wrote (a checkpoint's segment, a sweep's
    chunk): at least `keys`, each `length` long if given. A damaged file is an
    `InputError` naming it and what removing it does ("remove it to `redo`")."""
    try:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        missing = [k for k in keys if k not in arrays]
        if missing:
            raise KeyError(f"no {missing[0]!r}")
        if length is not None and any(len(v) != length for v in arrays.values()):
            raise ValueError(f"not {length} entries long")
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as err:
        raise InputError(f"{path} is damaged ({type(err).__name__}: {err}); remove it to {redo}") from None
    return arrays


def atomic_write(path, write) -> None:
    """`write(binary file)` into a temporary file in the same folder, then rename."""
    path = pathlib.Path(path)
    tmp, fd = _new_partial(lambda: tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")[::-1])
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o666 & ~_umask())
        with _COMMIT:
            if pathlib.Path(tmp) in _PARTIAL:  # else discarded by an interruption
                os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        _PARTIAL.discard(pathlib.Path(tmp))


def check_output_folder(out, overwrite: bool, argument: str = "out") -> pathlib.Path:
    """Fail early (an `InputError` naming `argument`) if `out` cannot be written or would
    be clobbered (a non-empty folder, unless `overwrite`)."""
    out = pathlib.Path(out)
    if out.name in ("", ".."):  # ".", "/", "..": no folder of its own to put in place
        raise InputError(f"`{argument}` {out}: name the output folder itself, not ., .. or /")
    if out.exists() and not out.is_dir():
        raise InputError(f"`{argument}` {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(f"`{argument}` {out}: folder exists and is not empty (pass `overwrite` to replace it)")
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"`{argument}` {out}: cannot create folder {parent} ({err.strerror})") from None
    if not os.access(parent, os.W_OK):
        raise InputError(f"`{argument}` {out}: cannot write in {parent}")
    lock_output(out, argument)
    return out


def lock_output(out, argument: str = "out") -> None:
    """Claim `out` for this process (a lock file beside it, held until `release_outputs`):
    a second command writing the same folder is an `InputError`, not a mixed result."""
    out = pathlib.Path(out)
    lock = out.resolve().parent / f".{out.name}.lock"
    if lock in _LOCKS:
        return
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
    except OSError as err:  # e.g. a read-only or virtual file system that os.access calls writable
        raise InputError(f"`{argument}` {out}: cannot write in {lock.parent} ({err.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise InputError(f"`{argument}` {out}: another jaxtissue command (pid {holder}) is writing this folder; "
                         "wait for it or choose another folder") from None
    os.ftruncate(fd, 0)
    os.write(fd, str(os.getpid()).encode())
    _LOCKS[lock] = fd


def ending() -> bool:
    """Whether `release_outputs(ending=True)` ran: the process is ending on a signal."""
    return bool(_ENDING)


def release_outputs(ending: bool = False) -> None:
    """Remove the temporary folders of unfinished outputs and release the locks
    (`lock_output`): what an interrupted command leaves is what it had before.
    `ending`: the process ends now; other threads make no new partial output."""
    with _COMMIT:
        if ending:
            _ENDING.append(True)
        for tmp in list(_PARTIAL):
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
        _PARTIAL.clear()
        for lock, fd in list(_LOCKS.items()):
            with contextlib.suppress(OSError):
                os.unlink(lock)
            os.close(fd)
        _LOCKS.clear()


@contextlib.contextmanager
def output_folder(out, overwrite: bool = False, argument: str = "out"):
    """Yield a temporary sibling folder; on success it replaces `out` in one rename
    (`argument`: the name errors give `out`).

    If anything fails, the temporary folder is removed and `out` is untouched."""
    out = check_output_folder(out, overwrite, argument)  # (and claims it, `lock_output`)
    tmp, _ = _new_partial(lambda: (tempfile.mkdtemp(dir=out.resolve().parent, prefix=f".{out.name}.partial-"), None))
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _PARTIAL.discard(tmp)
        raise
    with _COMMIT:
        if tmp not in _PARTIAL:  # discarded by an interruption
            return
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        _PARTIAL.discard(tmp)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_netcdf(dataset, path) -> None:
    """`dataset` to NetCDF-4 via a temporary file, then rename: an `xarray.Dataset`
    (xarray's h5netcdf engine), or `(variables, attrs)` as `Result.contents` gives them,
    written with h5netcdf alone into the file xarray would write (without importing
    xarray, which imports dask's arrays and scheduler to check for them: ~0.5 s)."""
    path = pathlib.Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    if isinstance(dataset, tuple):
        _write_contents(*dataset, tmp)
    else:
        dataset.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, path)


def _write_contents(variables: dict, attrs: dict, path) -> None:
    """{name: (dims, values, attrs)} and global `attrs` as a NetCDF-4 file: each dimension
    sized by the first variable that has it; floats with xarray's default fill value (NaN)."""
    import h5netcdf

    with h5netcdf.File(path, "w") as f:
        for name, (dims, values, _) in variables.items():
            for dim, size in zip(dims, np.shape(values)):
                if dim not in f.dimensions:
                    f.dimensions[dim] = size
        for name, (dims, values, var_attrs) in variables.items():
            values = np.asarray(values)
            fill = {"fillvalue": np.nan} if values.dtype.kind == "f" else {}
            var = f.create_variable(name, dims, values.dtype, data=values, **fill)
            var.attrs.update(var_attrs)
        f.attrs.update(attrs)
