"""Bayesian calibration of a calibration problem: the log likelihood's gradient, the
`calibrate --posterior` command and its files, held-out conditions, `predict`, fitted
files at their own resolution, design under uncertainty, and reproduce's bands."""

import dataclasses
import json
import math

import jax
import numpy as np
import pytest

from jaxtissue.io import InputError
from jaxtissue.studies import posterior as post

# ---- the calibration problem's posterior and the command

HEADER = "observableId,simulationConditionId,time,measurement,noiseParameters,unit,source\n"
WEEK = 604800.0


@pytest.fixture(scope="module")
def static_problem(tmp_path_factory):
    """A small static problem: DNA and collagen at 1–3 weeks, with SDs of 5 %, from the
    default parameters; k_m0 and E_m0 free (E_m0 unseen by these data). A second
    condition, "repeat", holds the same culture's 3-week collagen: what the posterior
    command holds out and predicts."""
    from helpers import TINY_MODEL

    import jaxtissue as jt
    from jaxtissue.studies import calibration as cal

    folder = tmp_path_factory.mktemp("posterior")
    r = jt.simulate(jt.Params(), jt.Protocol.static(), 3 * WEEK, jt.Grid(1, 8), coupling_interval_s=WEEK)
    rows = []
    for q, unit in (("dna_ug_per_g", "ug/g"), ("collagen_mg_per_g", "mg/g")):
        for w in (1, 2, 3):
            v = float(getattr(r, q)[r.index(w * WEEK)])
            rows.append(f"{q},static,{w * WEEK},{v!r},{0.05 * v!r},{unit},\n")
    v = float(r.collagen_mg_per_g[r.index(3 * WEEK)])
    rows.append(f"collagen_mg_per_g,repeat,{3 * WEEK},{v!r},{0.05 * v!r},mg/g,\n")
    (folder / "m.csv").write_text(HEADER + "".join(rows))
    (folder / "problem.toml").write_text(
        'measurements = "m.csv"\n[parameters.free]\n'
        'k_m0 = { bounds = [5e-8, 1e-6], transform = "log" }\n'
        'E_m0_kPa_per_ug_g = { bounds = [0.2, 5.0], transform = "linear", prior = { normal = [1.0, 0.5] } }\n'
        '[conditions.static]\nregime = "static"\n[conditions.repeat]\nregime = "static"\n' + TINY_MODEL + "[fit]\nstarts = 1\nmax_steps = 20\nprofile_points = 2\n")
    return cal.read_problem(folder / "problem.toml"), folder


def test_log_likelihood_gradient_matches_central_differences(static_problem):
    problem, _ = static_problem
    # tight tolerances: central differences of an adaptive solve carry its error / step
    problem = dataclasses.replace(problem, model=dataclasses.replace(problem.model, rtol=1e-8, atol=1e-11))
    value_and_grad = jax.jit(jax.value_and_grad(post.log_likelihood_t(problem)))  # one program for both
    t = problem.t_from_values([1.5e-7, 1.2])
    ad = np.asarray(value_and_grad(t)[1])
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-4
        fd = (float(value_and_grad(t + e)[0]) - float(value_and_grad(t - e)[0])) / 2e-4
        assert ad[i] == pytest.approx(fd, rel=1e-4, abs=1e-8), i


def _named_by(problem, settings, phases, which, x):
    """A program taking what `post.whitened_programs`' take as static arguments."""
    return x * settings.chains + phases + which + len(problem.free)


def test_the_samplers_programs_are_named_by_the_problem_and_its_settings(static_problem, tmp_path, monkeypatch):
    """`whitened_programs` take the problem, the sampler's settings and the warmup's parts
    as static arguments (`cache.call`): for a problem read from its file they name a
    saved program, which a second process (here: the programs in memory forgotten,
    compiling forbidden, the problem read again) loads (the cheap version of
    test_a_second_posterior_loads_its_sampler)."""
    import equinox as eqx

    from jaxtissue import cache
    from jaxtissue.studies import calibration as cal

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    problem, folder = static_problem
    settings, x, program = post.SamplerSettings(chains=2), np.arange(3.0), eqx.filter_jit(_named_by)
    with cache.saved_executables(tmp_path):
        cache.call(program, problem, settings, 3, 0, x)
        assert len(list(tmp_path.glob("*.jtx"))) == 1
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            m.setattr(cache, "_compile", lambda *a: pytest.fail("compiled again"))
            again = cal.read_problem(folder / "problem.toml")
            np.testing.assert_array_equal(cache.call(program, again, post.SamplerSettings(chains=2), 3, 0, x + 1.0), (x + 1.0) * 2 + 5)


@pytest.mark.slow  # compiles the sampler's programs; the test above is its cheap version
def test_a_second_posterior_loads_its_sampler(static_problem, tmp_path, monkeypatch):
    """Where the command line saves programs, a second process's sampler (here: the
    programs in memory forgotten, tracing and compiling forbidden) loads its warmup's and
    draws' programs and draws the same."""
    from jaxtissue import cache

    monkeypatch.delenv("JAXTISSUE_NO_SAVED_PROGRAMS", raising=False)
    problem, _ = static_problem
    t = problem.t_from_values([1.7e-7, 1.0])
    jac = jax.jacfwd(problem.residuals)(t)
    settings = post.SamplerSettings(chains=2, warmup=40, samples=20)
    with cache.saved_executables(tmp_path):
        first = post.sample(problem, t, jac, settings)
        assert len(list(tmp_path.glob("*.jtx"))) == 3  # the ridge's profile solves, the warmup's and the draws'
        monkeypatch.setattr(cache, "_loaded", {})
        with monkeypatch.context() as m:
            for where, name in ((cache, "_compile"), (post, "log_density_fn")):
                m.setattr(where, name, lambda *a, name=name, **k: pytest.fail(f"{name} again"))
            again = post.sample(problem, t, jac, settings)
    np.testing.assert_array_equal(again.u, first.u)


@pytest.fixture(scope="module")
def sampled(static_problem):
    """`jaxtissue calibrate --posterior` on the small problem: its folder and stdout."""
    import contextlib
    import io

    from jaxtissue.cli import main

    _, folder = static_problem
    out = folder / "fit"
    argv = ["calibrate", str(folder / "problem.toml"), "--no-profiles", "--posterior", "--chains", "2", "--warmup", "40",
            "--samples", "40", "--hold-out", "repeat", "--out", str(out)]
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main(argv) == 0
    return out, stdout.getvalue()


def test_calibrate_posterior_command_writes_inference_data(static_problem, sampled):
    import arviz as az

    problem, _ = static_problem
    out, stdout = sampled
    assert "posterior: 80 draws" in stdout
    idata = az.from_netcdf(out / "posterior.nc")
    assert {"posterior", "sample_stats", "observed_data", "posterior_predictive"} <= set(idata.groups())
    assert idata.posterior["k_m0"].shape == (2, 40) and "diverging" in idata.sample_stats
    np.testing.assert_allclose(idata.observed_data["y"].values, problem.data()[0][:-1])  # the repeat held out
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["posterior"]) == {"k_m0", "E_m0_kPa_per_ug_g"}
    for n, v in summary["posterior"].items():
        assert {"mean", "sd", "q05", "q50", "q95", "r_hat", "ess_bulk"} <= set(v) and v["q05"] <= v["q50"] <= v["q95"]
        assert v["r_hat"] == pytest.approx(float(az.rhat(idata.posterior)[n]), rel=1e-12)  # unrounded: 1.009 passes < 1.01
    assert summary["posterior"]["k_m0"]["constrained_by"] == "data"  # the data see k_m0 …
    assert summary["posterior"]["E_m0_kPa_per_ug_g"]["constrained_by"] == "prior"  # … not the modulus
    assert {"divergences", "sampling_seconds", "predictive_check"} <= set(summary)
    assert "## Posterior (NUTS)" in (out / "report.md").read_text()
    [held] = summary["held_out"]  # the repeat culture, predicted from the static data's posterior
    assert held["observation"].startswith("collagen_mg_per_g|repeat") and held["inside"] and held["lower"] < held["data"] < held["upper"]
    assert "held out collagen_mg_per_g|repeat" in stdout and len(summary["observations"]) == 6
    assert {"pairs.png", "traces.png"} <= {p.name for p in out.iterdir()}


def test_sampler_sizes_beyond_memory_are_one_line_before_the_fit(static_problem, tmp_path, capsys):
    from jaxtissue.cli import main

    _, folder = static_problem
    for flags, message in ((["--samples", "1000000000"], "--chains, --warmup, --samples: chains x samples = 4 x 1000000000 = 4e+09 draws; at most 10000000"),
                           (["--chains", "10000000", "--samples", "1", "--warmup", "1"], "the posterior (10000000 simultaneous runs on the 2 x 8 grid) needs about")):
        assert main(["calibrate", str(folder / "problem.toml"), "--posterior", *flags, "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
        assert not (tmp_path / "o").exists()


def test_hold_out_refuses_what_it_cannot_do(static_problem):
    problem, _ = static_problem
    with pytest.raises(InputError, match="`hold_out` = 'flex': no observation of that condition; allowed: repeat, static"):
        post.hold_out(problem, "flex")
    with pytest.raises(InputError, match="no observation left to calibrate on"):
        post.hold_out(post.hold_out(problem, "repeat")[0], "static")


def test_calibrate_posterior_bad_flags_exit_2(static_problem, capsys):
    from jaxtissue.cli import main

    _, folder = static_problem
    with pytest.raises(SystemExit) as exit_:
        main(["calibrate", str(folder / "problem.toml"), "--posterior", "--chains", "0", "--out", str(folder / "x")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--chains" in err and not (folder / "x").exists()
    assert main(["calibrate", str(folder / "problem.toml"), "--hold-out", "repeat", "--out", str(folder / "x")]) == 2
    assert "--hold-out needs --posterior" in capsys.readouterr().err and not (folder / "x").exists()


def test_predict_command_gives_bands_that_hold_the_draws(sampled, capsys):
    import xarray as xr

    from jaxtissue.cli import main

    folder, _ = sampled
    out = folder.parent / "predicted"
    assert main(["predict", "--posterior", str(folder), "--regime", "static", "--t-end", str(2 * WEEK), "--draws", "6",
                 "--out", str(out)]) == 0
    assert "collagen_mg_per_g at" in capsys.readouterr().out
    ds = xr.open_dataset(out / "predict.nc", engine="h5netcdf")
    assert ds["collagen_mg_per_g"].shape[0] == 6 and ds["time_s"].values[-1] == pytest.approx(2 * WEEK)
    c = ds["collagen_mg_per_g"].values
    assert np.all(ds["collagen_mg_per_g_q05"].values <= ds["collagen_mg_per_g_q95"].values)
    np.testing.assert_allclose(ds["collagen_mg_per_g_q50"].values, np.median(c, axis=0))
    assert not ds["failed"].values.any() and np.ptp(c[:, -1]) > 0  # the draws differ, so does their collagen
    summary = json.loads((out / "summary.json").read_text())
    assert summary["draws"] == 6 and "collagen_mg_per_g" in summary["at_t_end"] and summary["warnings"] == []
    assert (out / "bands.png").is_file()


def _broken(folder):
    (folder / "broken").mkdir(exist_ok=True)
    (folder / "broken" / "posterior.nc").write_text("not NetCDF")
    return folder / "broken"


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "nowhere", "no posterior.nc there"),
    (_broken, "not a jaxtissue posterior"),
])
def test_predict_without_a_posterior_exits_2(sampled, capsys, make, message):
    from jaxtissue.cli import main

    folder, _ = sampled
    source = make(folder.parent)
    out = folder.parent / "never"
    assert main(["predict", "--posterior", str(source), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--posterior" in err and message in err and not out.exists()


def test_fitted_file_simulates_at_the_fit_resolution_and_reproduces_the_report(sampled, capsys):
    """`jaxtissue simulate --params fitted.toml` uses the fit's [model] table and gives
    the model values the calibration reported, within 0.5 %."""
    from jaxtissue.cli import main

    folder, _ = sampled
    out = folder.parent / "simulated"
    assert main(["simulate", "--regime", "static", "--t-end", str(3 * WEEK), "--params", str(folder / "fitted.toml"),
                 "--out", str(out)]) == 0
    assert "model resolution from" in capsys.readouterr().out
    run = json.loads((out / "summary.json").read_text())
    reported = json.loads((folder / "summary.json").read_text())["observations"]
    for o in reported:
        simulated = run[o["name"]][run["times_s"].index(o["time_s"])]
        assert simulated == pytest.approx(o["model"], rel=5e-3), o


ROBUST = """
objective = "total_collagen"
t_end_s = 1814400.0
[constraints]
post_force_max_N = 0.02
[uncertainty]
posterior = "{posterior}"
{extra}
[optimizer]
starts = 1
steps = 4
learning_rate = 0.3
inner_steps = 2
grid_points = 3
""" + "\n[model]\nny = 8\nflex_nx = 2\nbeam_segments = 8\nbeam_steps_per_cycle = 24\ncoupling_interval_s = 604800.0\n"


@pytest.mark.parametrize("extra, message", [
    ('risk = "quantile"\nquantile = 1.5', "[uncertainty] quantile = 1.5 must be a number in (0, 1)"),
    ("constraint_probability = 0", "constraint_probability = 0 must be a number in (0, 1)"),
    ('risk = "worst"', "risk = 'worst'; allowed: 'mean', 'quantile'"),
    ("draws = 70\ncheck_draws = 20", "draws + check_draws = 90 exceeds the posterior's 80 draws"),
    ("constraint_probability = 0.95\ndraws = 16", "draws = 16 is too few for constraint_probability = 0.95"),
])
def test_bad_uncertainty_tables_exit_2(sampled, capsys, extra, message):
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust_bad.toml"
    problem.write_text(ROBUST.format(posterior=folder.name, extra=extra))
    out = folder.parent / "never"
    assert main(["optimize", str(problem), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and not out.exists()


def test_uncertainty_needs_a_posterior_there(sampled, capsys):
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust_missing.toml"
    problem.write_text(ROBUST.format(posterior="no_such_folder", extra=""))
    assert main(["optimize", str(problem), "--out", str(folder.parent / "never")]) == 2
    assert "[uncertainty] posterior = " in capsys.readouterr().err


@pytest.mark.slow
def test_robust_design_meets_its_declared_probability_on_fresh_draws(sampled):
    """A chance-constrained design over 9 posterior draws, checked on 40 fresh ones
    beside the point-estimate optimum."""
    from jaxtissue.cli import main

    folder, _ = sampled
    problem = folder.parent / "robust.toml"
    problem.write_text(ROBUST.format(posterior=folder.name, extra='risk = "quantile"\nquantile = 0.1\n'
                                                                     "constraint_probability = 0.9\ndraws = 9\ncheck_draws = 40"))
    out = folder.parent / "robust_out"
    assert main(["optimize", str(problem), "--out", str(out), "--no-progress"]) == 0
    r = json.loads((out / "summary.json").read_text())["robust"]
    for key in ("robust_optimum", "point_estimate_optimum"):
        assert {"objective", "objective_mean", "constraint_probability", "protocol"} <= set(r[key])
    p = r["robust_optimum"]["constraint_probability"]
    print(f"fresh draws: robust optimum meets the limit in {p:.2f}, the point-estimate optimum in "
          f"{r['point_estimate_optimum']['constraint_probability']:.2f} (declared 0.9)")
    assert p >= 0.9 - 2 * math.sqrt(0.09 / 40)
    assert "## Under uncertainty" in (out / "report.md").read_text()


def test_reproduce_bands_from_a_posterior_folder(sampled):
    """`reproduce.calibrated_bands`: the static and flex cases over posterior draws (as
    many, as long, as the predict command's above: its static program serves)."""
    import jaxtissue as jt

    folder, _ = sampled
    bands = jt.reproduce.calibrated_bands(t_end_s=2 * WEEK, draws=6, folder=folder)
    assert set(bands) == {"static", "flex"}
    for b in bands.values():
        assert b["draws"] == 6 and b["failed"] == 0 and b["time_s"][-1] == pytest.approx(2 * WEEK) and b["r_hat_max"] > 0
        lo, mid, hi = b["collagen_mg_per_g"]
        assert np.all(lo <= mid) and np.all(mid <= hi) and mid[-1] > 0
    assert bands["flex"]["post_force_max_N"][1][-1] > 0 == bands["static"]["post_force_max_N"][1][-1]
    assert jt.reproduce.calibrated_bands(folder=folder.parent / "none") is None
