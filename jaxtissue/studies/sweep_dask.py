"""Sweeps on a Dask cluster (dask.distributed), written into a Zarr store.

Each chunk of a `Sweep` is one Dask task: in a worker process, one jitted, vmapped
batch (`sweep.batched`, compiled once per worker, or loaded where the client saves its
programs: `run_chunk_saving`). The client writes each finished
chunk into `DIR/sweep.zarr` by region (`xarray.Dataset.to_zarr(region=...)`) and marks
it done, so that `resume=True` skips the regions already written; at the end it writes
`DIR/sweep.nc`, the file a serial run writes. Dask re-runs the tasks of a worker that
is lost. `cluster="local:N"` starts a `LocalCluster` of N single-threaded worker
processes; any other value is a scheduler's address (`tcp://host:8786`), e.g. of a
dask-jobqueue cluster on SLURM (docs/numerics.md).
"""

from __future__ import annotations

import contextlib
import json
import pathlib
import re

import numpy as np

from .. import cache
from ..io import InputError, RunError, write_netcdf
from ..result import SCALARS
from .sweep import Sweep, fingerprint, run_chunk, to_dataset

STORE = "sweep.zarr"


class ClusterError(RunError):
    """A Dask cluster that could not be started."""


def check_cluster(cluster: str) -> int | None:
    """The number of local workers of `"local:N"`, None for a scheduler address; an
    `InputError` for anything else."""
    local = re.fullmatch(r"local:(\d+)", cluster)
    if local:
        n = int(local.group(1))
        if not 1 <= n <= 256:
            raise InputError(f"`dask` = {cluster!r}: local:N needs 1 <= N <= 256 worker processes")
        return n
    if not re.fullmatch(r"[a-z]+://[^\s/]+(:\d+)?", cluster):
        raise InputError(f"`dask` = {cluster!r}: expected local:N or a scheduler address such as tcp://host:8786")
    return None


@contextlib.contextmanager
def client(cluster: str):
    """A `dask.distributed.Client` for `"local:N"` (a new LocalCluster of N worker
    processes, one thread each, shut down with the client) or a scheduler address
    (`check_cluster`), as a context."""
    from dask.distributed import Client, LocalCluster

    n = check_cluster(cluster)
    if n is not None:
        try:
            local = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None)
        except (RuntimeError, OSError, TimeoutError) as err:  # e.g. a worker process that dies while starting
            raise ClusterError(f"the Dask cluster {cluster} did not start ({err})") from None
        with local, Client(local) as dask:  # a client given a cluster leaves it running
            yield dask
        return
    try:
        remote = Client(cluster)  # waits up to dask's distributed.comm.timeouts.connect
    except OSError as err:
        raise InputError(f"`dask` = {cluster!r}: no scheduler there ({err})") from None
    with remote:
        yield remote


def _empty_store(sweep: Sweep, store: pathlib.Path, stamp: dict) -> None:
    import xarray as xr

    n, width = sweep.size, sweep.chunk
    extra = sweep.times().size if sweep.outputs == "series" else None
    shape = (n,) if extra is None else (n, extra)
    dims = ("point",) if extra is None else ("point", "time_s")
    ds = xr.Dataset({k: (dims, np.full(shape, np.nan)) for k in SCALARS})
    ds["failed"] = ("point", np.zeros(n, bool))
    ds["chunk_done"] = ("chunk", np.zeros(-(-n // width), bool))
    ds.attrs["jaxtissue_sweep"] = json.dumps(stamp)
    encoding = {k: {"chunks": (width,) + (() if extra is None else (extra,))} for k in SCALARS}
    encoding |= {"failed": {"chunks": (width,)}, "chunk_done": {"chunks": (1,)}}
    ds.to_zarr(store, mode="w", encoding=encoding, consolidated=False)


def _write_region(store: pathlib.Path, start: int, width: int, result: dict) -> None:
    import xarray as xr

    n = len(result["failed"])
    data = {k: (("point",) + (("time_s",) if np.ndim(result[k]) > 1 else ()), np.asarray(result[k], float)) for k in SCALARS}
    data["failed"] = ("point", np.asarray(result["failed"], bool))
    xr.Dataset(data).to_zarr(store, region={"point": slice(start, start + n)}, consolidated=False)
    done = xr.Dataset({"chunk_done": ("chunk", np.ones(1, bool))})
    done.to_zarr(store, region={"chunk": slice(start // width, start // width + 1)}, consolidated=False)  # after the values


def run_chunk_saving(sweep: Sweep, start: int, programs: pathlib.Path | None):
    """`run_chunk` in a worker, its program loaded from or saved in the client's folder
    of saved programs `programs` (`cache.saved_folder`; None: compiled in memory), so
    that the workers of a later sweep of the same model load it."""
    with cache.saved_executables(programs):
        return run_chunk(sweep, start)


def run(sweep: Sweep, out, cluster: str, resume: bool = False, progress: bool = False):
    """Run every chunk not yet in `out/sweep.zarr` as a Dask task on `cluster`, then
    write `out/sweep.nc`. Returns the `xarray.Dataset` (equal to `sweep.run`'s)."""
    import xarray as xr
    from dask.distributed import as_completed
    from tqdm.auto import tqdm

    out = pathlib.Path(out)
    store = out / STORE
    stamp = {"fingerprint": fingerprint(sweep), "size": sweep.size, "chunk": sweep.chunk}
    fresh = not (resume and store.exists())
    if not fresh:
        try:  # all of it read now: a damaged store is found before any chunk is computed
            held = xr.open_zarr(store, consolidated=False).load()
            missing = [k for k in (*SCALARS, "failed", "chunk_done") if k not in held]
            if missing:
                raise KeyError(f"no variable {missing[0]!r}")
            held_stamp = json.loads(held.attrs.get("jaxtissue_sweep", "{}"))
            done = np.asarray(held["chunk_done"].values)
        except Exception as err:  # noqa: BLE001 - zarr's and xarray's errors for a damaged store have no common base
            raise InputError(f"`resume` {out}: {store} is damaged ({type(err).__name__}: {err}); "
                             f"remove it to start the sweep again") from None
        if held_stamp != stamp:
            raise InputError(f"`resume` {out}: the folder holds a different sweep (its file or chunk size changed)")
    else:
        done = np.zeros(-(-sweep.size // sweep.chunk), bool)
    starts = [k * sweep.chunk for k in range(len(done)) if not done[k]]
    with client(cluster) as dask, tqdm(total=len(done), initial=int(done.sum()), desc="sweep", unit="chunk",
                                       disable=not progress) as bar:
        if fresh:  # the store once the cluster is there: a cluster that fails leaves nothing
            out.mkdir(parents=True, exist_ok=True)
            _empty_store(sweep, store, stamp)
        programs = cache.saved_folder()
        futures = {dask.submit(run_chunk_saving, sweep, s, programs, pure=False): s for s in starts}
        for future in as_completed(futures):
            _write_region(store, futures[future], sweep.chunk, future.result())
            bar.update(1)
    held = xr.open_zarr(store, consolidated=False).load()
    merged = {k: held[k].values for k in (*SCALARS, "failed")}
    ds = to_dataset(sweep, merged)
    write_netcdf(ds, out / "sweep.nc")
    return ds
