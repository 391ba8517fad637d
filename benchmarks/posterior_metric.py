"""How well the sampler's coordinates fit the Engelmayr posterior: the covariance of
the shipped posterior's draws (jaxtissue/studies/engelmayr2005_posterior) in the
sampler's whitened coordinates z, for three choices made at the fit's optimum (that
folder's fitted.toml). Eigenvalues all 1 would be a perfect fit; their ratio (the
condition number) is what NUTS pays for in step size and trajectory length.

* u = c + L z, L Lᵀ the Laplace covariance in u, (Dᵀ JᵀJ D + Σ₀⁻¹)⁻¹ with D = dt/du;
* u = c + L z, L Lᵀ the Laplace covariance of t, (JᵀJ + Σ₀⁻¹)⁻¹ (`posterior.laplace_inverse_mass`);
* the ridge coordinates `calibrate --posterior` samples in (`posterior.whitening`).

It also prints the ridges' profiles (the leaders' knots and χ²) and, at ten draws spread
over k_c,max, the posterior's narrowest local standard deviation in u (the Hessian of
ln p by central differences of its gradient) and its direction.

    python benchmarks/posterior_metric.py
"""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxtissue.io import read_params_toml  # noqa: E402
from jaxtissue.studies import posterior as post  # noqa: E402
from jaxtissue.studies.calibration import read_problem  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "jaxtissue" / "studies" / "engelmayr2005_posterior"


def main():
    problem = read_problem(ROOT / "calibrate" / "engelmayr2005.toml")
    names = problem.names
    fitted = read_params_toml(SHIPPED / "fitted.toml")
    t_best = np.asarray(problem.t_from_values(jnp.asarray([getattr(fitted, n) for n in names])))
    J = np.asarray(jax.jit(jax.jacfwd(problem.residuals))(jnp.asarray(t_best)))
    values = post.read_saved(SHIPPED).values.reshape(-1, len(names))
    t = np.asarray(jax.vmap(problem.t_from_values)(jnp.asarray(values)))
    u = np.asarray(post.u_from_t(problem.free, jnp.asarray(t)))
    print(f"{len(u)} shipped draws; optimum {dict(zip(names, np.round(np.exp(t_best), 9)))}")

    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    D = np.diag(np.exp(np.asarray(post.log_dt_du(problem.free, post.u_from_t(problem.free, t_best)))))
    in_u = np.linalg.inv(D @ J.T @ J @ D + np.diag(12.0 / (hi - lo) ** 2))
    of_t = post.laplace_inverse_mass(problem, t_best, J)
    white = post.whitening(problem, t_best, J)
    for n, ridge in enumerate(white.ridges):
        print(f"{('first', 'second')[n]} ridge: leader {names[ridge.leader]}, sheared {post.straightens(ridge)}")
        for at, x, chi2 in zip(ridge.at, ridge.x, ridge.chi2):
            where = f" with {names[ridge.held]} held at {at:.2f}" if ridge.held != ridge.leader else ""
            print(f"  knots (ln){where}: {np.round(x[np.isfinite(chi2)], 2)}, profile chi2 {np.round(chi2[np.isfinite(chi2)], 2)}")
    c_opt = np.asarray(post.u_from_t(problem.free, jnp.asarray(t_best)))
    for name, c, L, w in (("Laplace covariance in u", c_opt, np.linalg.cholesky(in_u), u),
                          ("Laplace covariance of t", c_opt, np.linalg.cholesky(of_t), u),
                          ("ridge coordinates", white.c, white.L, np.asarray(post.w_from_u(problem.free, white.args()[2], jnp.asarray(u))))):
        z = np.linalg.solve(L, (w - c).T).T
        e = np.linalg.eigvalsh(np.cov(z, rowvar=False))
        print(f"{name:24s} eigenvalues of the draws' covariance in z {np.array2string(e, precision=3)}, "
              f"condition number {e.max() / e.min():.0f}")

    grad = jax.jit(jax.vmap(jax.grad(post.log_density_fn(problem))))
    k, h = len(names), 1e-4
    i_kc = names.index("k_c_max") if "k_c_max" in names else 0
    picks = np.argsort(t[:, i_kc])[np.linspace(0, len(t) - 1, 10).astype(int)]
    print(f"narrowest local SD of the posterior in u, at draws spread over {names[i_kc]}:")
    for j in picks:
        steps = np.concatenate([u[j] + h * s * np.eye(k)[m] for m in range(k) for s in (1, -1)]).reshape(-1, k)
        g = np.asarray(grad(jnp.asarray(steps))).reshape(k, 2, k)
        H = -(g[:, 0] - g[:, 1]) / (2 * h)
        e, V = np.linalg.eigh(0.5 * (H + H.T))
        v = V[:, -1] * np.sign(V[np.argmax(np.abs(V[:, -1])), -1])
        print(f"  at {', '.join(f'{n} {x:.2f}' for n, x in zip(names, t[j]))}: {1 / np.sqrt(e[-1]):.4f} "
              f"along {np.array2string(v, precision=2)}")


if __name__ == "__main__":
    main()
