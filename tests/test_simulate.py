"""End-to-end static culture against the independent SciPy solution, and the API."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy_reference
from helpers import SMALL_FLEX

import jaxtissue as jt
from jaxtissue.protocol import save_times


@pytest.fixture(scope="module")
def fine_static():
    return jt.simulate(jt.paper_parameters(), jt.Protocol.static(), t_end_s=2.0e6, grid=jt.Grid(ny=200))


def test_three_week_values_match_scipy_method_of_lines(fine_static):
    ref = scipy_reference.three_week_values(ny=400)
    i = fine_static.index(jt.THREE_WEEKS_S)
    assert float(fine_static.ts[i]) == jt.THREE_WEEKS_S
    for key in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa"):
        ours = float(getattr(fine_static, key)[i])
        assert ours == pytest.approx(float(ref[key]), rel=5e-3), key
        assert ours == pytest.approx(float(ref[key]), rel=1e-3), key  # in fact far closer


def test_save_times():
    ts = save_times(2.0e6, 2.0e4)
    assert ts[0] == 0 and ts[-1] == 2.0e6 and jt.THREE_WEEKS_S in ts
    assert np.all(np.diff(ts) > 0) and len(ts) == 102
    assert jt.THREE_WEEKS_S not in save_times(1.0e6, 2.0e4)


def test_initial_values_and_trends(fine_static):
    r = fine_static
    assert float(r.dna_ug_per_g[0]) == pytest.approx(536.0)
    assert float(r.collagen_mg_per_g[0]) == 0.0
    assert float(r.E_eff_kPa[0]) == pytest.approx(174.0)
    assert np.all(np.diff(np.asarray(r.collagen_mg_per_g)) >= 0)  # ECM only accumulates
    assert np.all(np.diff(np.asarray(r.EI_N_m2)) >= 0)
    assert not bool(r.failed)
    # ECM forms near the surfaces, where O2 exceeds the threshold (Fig. 5)
    m = np.asarray(r.profile_m[-1])
    assert m[0] > m[len(m) // 2] and m[-1] > m[len(m) // 2]


def test_to_xarray_has_units(fine_static):
    ds = fine_static.to_xarray()
    assert ds["collagen_mg_per_g"].attrs["units"] == "mg/g"
    assert ds["time_s"].attrs["units"] == "s"
    assert ds["profile_m"].dims == ("time_s", "y_cm")
    assert ds.attrs["k_c_max"] == pytest.approx(1.24e-5)


def test_result_file_is_the_file_xarray_writes(fine_static, tmp_path):
    """result.nc, written from `Result.contents` by h5netcdf alone, reads back as
    `to_xarray` gives the run and as the file xarray writes from it, fill values
    included; an `xarray.Dataset` goes through xarray."""
    import xarray as xr

    from jaxtissue import io

    io.write_netcdf(fine_static.contents(), tmp_path / "direct.nc")
    io.write_netcdf(fine_static.to_xarray(), tmp_path / "xarray.nc")
    direct, via_xarray = (xr.open_dataset(tmp_path / f"{n}.nc", engine="h5netcdf").load() for n in ("direct", "xarray"))
    xr.testing.assert_identical(direct, fine_static.to_xarray())
    xr.testing.assert_identical(direct, via_xarray)
    fills = [{n: str(d[n].encoding.get("_FillValue")) for n in d.variables} for d in (direct, via_xarray)]
    assert fills[0] == fills[1] and set(fills[0].values()) == {"nan"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["direct.nc", "xarray.nc"]  # no temporary file left


def test_jit_and_vmap_over_parameters():
    grid = jt.Grid(ny=16)
    base = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    k_m0s = jnp.array([1.0e-7, 1.675e-7, 3.0e-7])
    batched = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (3,)), base)
    batched = jax.tree_util.tree_map(lambda x: x, batched.replace(k_m0=k_m0s))
    run = jax.jit(jax.vmap(lambda p: jt.simulate(p, t_end_s=5e5, grid=grid).collagen_mg_per_g[-1]))
    out = run(batched)
    singles = [float(jt.simulate(base.replace(k_m0=k), t_end_s=5e5, grid=grid).collagen_mg_per_g[-1]) for k in k_m0s]
    np.testing.assert_allclose(np.asarray(out), singles, rtol=1e-6)
    assert np.all(np.diff(np.asarray(out)) > 0)


def test_saving_only_the_end_gives_the_same_final_values():
    """`save="end"` (what sweeps of final values use) changes only what is kept."""
    p = jt.paper_parameters()
    flex = (jt.Protocol.flex(), jt.Grid(*SMALL_FLEX["grid_shape"]), SMALL_FLEX["t_end_s"])  # the series: the suite's shared program
    for protocol, grid, t_end in ((jt.Protocol.static(), jt.Grid(1, 16), 5e5), flex):
        full = jt.simulate(p, protocol, t_end, grid)
        end = jt.simulate(p, protocol, t_end, grid, save="end")
        assert end.ts == (t_end,) and end.collagen_mg_per_g.shape == (1,) and not bool(end.failed)
        for key in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa", "post_force_max_N", "profile_m"):
            np.testing.assert_allclose(getattr(end, key)[-1], getattr(full, key)[-1], rtol=1e-9, err_msg=key)  # round-off: the end state is not interpolated
    with pytest.raises(ValueError, match="save = 'all'"):
        jt.simulate(p, save="all")


def test_a_static_series_by_intervals_goes_on_with_the_step_it_ended_with():
    """`static_series="intervals"`: each interval's solve starts with the step the last
    one would have taken next (no jump at a save time), so the 91 intervals take about
    the dense run's steps (not ~6 each from `dt0_s` again), with the same series to the
    tolerance."""
    p, grid = jt.paper_parameters(), jt.Grid(1, 8)
    dense, intervals = (jt.simulate(p, t_end_s=jt.THREE_WEEKS_S, grid=grid, options=jt.SolverOptions(static_series=s))
                        for s in ("dense", "intervals"))
    assert len(intervals.ts) == 92 and int(intervals.num_steps) < 1.6 * int(dense.num_steps), (intervals.num_steps, dense.num_steps)
    for key in ("dna_ug_per_g", "collagen_mg_per_g", "E_eff_kPa"):
        np.testing.assert_allclose(getattr(intervals, key)[1:], getattr(dense, key)[1:], rtol=1e-4, err_msg=key)


def test_bad_arguments():
    with pytest.raises(ValueError, match="t_end_s"):
        jt.simulate(jt.paper_parameters(), t_end_s=-1.0)
    rodas = jt.SolverOptions(method="rodas4p2")  # its Jacobian must be exact: static, 1-D, no cell flux
    with pytest.raises(ValueError, match="static run on 2 x 8: use 'ros34pw2'"):
        jt.simulate(jt.paper_parameters(), grid=jt.Grid(nx=2, ny=8), options=rodas)
    with pytest.raises(ValueError, match="with cell flux"):
        jt.simulate(jt.paper_parameters(D_c=1e-9), grid=jt.Grid(ny=8), options=rodas)
    with pytest.raises(ValueError, match="method = 'rk4'; allowed: 'ros34pw2', 'rodas4p2'"):
        jt.SolverOptions(method="rk4")
    with pytest.raises(ValueError, match="grid ny"):
        jt.Grid(nx=1, ny=1)
    with pytest.raises(ValueError, match="regime"):
        jt.Protocol(regime="dynamic")
    with pytest.raises(TypeError, match=r"grid must be a jaxtissue Grid \(e.g. Grid\(nx=1, ny=40\)\), got tuple"):
        jt.simulate(jt.paper_parameters(), grid=(1, 8))
    for name, value in (("protocol", "flex"), ("beam", (4, 8)), ("options", {"rtol": 1e-6}), ("params", {"k_m0": 1e-7})):
        with pytest.raises(TypeError, match=rf"^{name} must be a jaxtissue \w+ \(e.g. .*\), got {type(value).__name__}$"):
            jt.simulate(**{"params": jt.paper_parameters(), name: value})
    for value in ("1e-7", None, True):  # NumPy would read "1e-7" as a number, and None as NaN
        with pytest.raises(TypeError, match=rf"^parameter k_m0 = {re.escape(repr(value))} must be a number \(1/s\)$"):
            jt.paper_parameters(k_m0=value)
    with pytest.raises(ValueError, match=r"^parameter o_m = 1.5 is outside its allowed range \(0, 1\): O2 threshold"):
        jt.paper_parameters(o_m=1.5)  # a fraction: no unit "(1)"
    with pytest.raises(TypeError, match=r"^protocol period_s = '1' must be a number$"):
        jt.Protocol.flex(period_s="1")
    with pytest.raises(TypeError, match=r"^parameter k_m0 = \[1e-07, 2e-07\] must be a number \(1/s\)$"):
        jt.paper_parameters(k_m0=[1e-7, 2e-7])  # a list would be two leaves of the pytree
    with pytest.raises(TypeError, match=r"^protocol period_s = \[1.0, 2.0\] must be a number$"):
        jt.Protocol.flex(period_s=[1.0, 2.0])
    for batch in (np.array([1e-7, 2e-7]), jnp.array([1e-7, 2e-7])):  # a batch is vmapped, not passed whole
        with pytest.raises(ValueError, match=r"^params.k_m0 has shape \(2,\); simulate runs one parameter set and protocol \(map a batch with jax.vmap"):
            jt.simulate(jt.paper_parameters(k_m0=batch), grid=jt.Grid(1, 8))
        with pytest.raises(ValueError, match=r"^protocol.period_s has shape \(2,\);.*stages: Protocol.schedule\)$"):
            jt.simulate(jt.paper_parameters(), jt.Protocol.flex(period_s=batch), grid=jt.Grid(2, 8))
    for t_end in (np.float32(2e4), jnp.asarray(2e4)):  # NumPy and 0-d JAX numbers are numbers
        short = jt.simulate(jt.paper_parameters(), t_end_s=t_end, grid=jt.Grid(1, 4), save="end")
        assert short.ts == (2e4,) and short.index(2e4) == 0
    with pytest.raises(ValueError, match=r"^t_s = 1.8144e\+06 s is outside this run's save times, 20000 to 20000 s$"):
        short.index(jt.THREE_WEEKS_S)  # not silently the last value
    for t_end in (-1.0, float("nan"), jnp.array([1e5, 2e5]), "2e6", True):
        with pytest.raises(ValueError, match=r"^t_end_s = .* must be a positive number of seconds$"):
            jt.simulate(jt.paper_parameters(), t_end_s=t_end)
    with pytest.raises(TypeError, match="t_end_s must be a concrete number of seconds, not a traced value"):
        jax.jit(lambda t: jt.simulate(jt.paper_parameters(), t_end_s=t).collagen_mg_per_g)(2e4)
    other = jt.State(*(jnp.ones((1, 10)) for _ in range(3)))
    with pytest.raises(ValueError, match=r"initial_state.o has shape \(1, 10\); the 1 x 8 grid needs \(1, 8\)"):
        jt.simulate(jt.paper_parameters(), grid=jt.Grid(1, 8), initial_state=other)
    with pytest.raises(TypeError, match="initial_state must be a jaxtissue State"):
        jt.simulate(jt.paper_parameters(), grid=jt.Grid(1, 8), initial_state=jnp.ones((3, 1, 8)))
