"""How well the sampler's starting metric fits the Engelmayr posterior: the covariance
of the shipped posterior's draws (jaxtissue/studies/engelmayr2005_posterior) in the
sampler's whitened coordinates z, u = c + L z, for three choices of L Lᵀ at the fit's
optimum (that folder's fitted.toml). Eigenvalues all 1 would be a perfect fit; their
ratio (the condition number) is what NUTS pays for in step size and trajectory length.

* the Laplace covariance in u, (Dᵀ JᵀJ D + Σ₀⁻¹)⁻¹ with D = dt/du at the optimum;
* the Laplace covariance of t, (JᵀJ + Σ₀⁻¹)⁻¹ (`posterior.laplace_inverse_mass`);
* that plus the covariance of the ridge's profile path (`posterior.whitening`).

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
    fitted = read_params_toml(SHIPPED / "fitted.toml")
    t_best = np.asarray(problem.t_from_values(jnp.asarray([getattr(fitted, n) for n in problem.names])))
    J = np.asarray(jax.jit(jax.jacfwd(problem.residuals))(jnp.asarray(t_best)))
    values = post.read_saved(SHIPPED).values.reshape(-1, len(problem.names))
    u = np.asarray(post.u_from_t(problem.free, jax.vmap(problem.t_from_values)(jnp.asarray(values))))
    draws = np.cov(u, rowvar=False)

    lo, hi = (np.asarray(b) for b in problem.t_bounds())
    D = np.diag(np.exp(np.asarray(post.log_dt_du(problem.free, post.u_from_t(problem.free, t_best)))))
    in_u = np.linalg.inv(D @ J.T @ J @ D + np.diag(12.0 / (hi - lo) ** 2))
    of_t = post.laplace_inverse_mass(problem, t_best, J)
    _, L = post.whitening(problem, t_best, J)
    print(f"{len(u)} shipped draws; optimum {dict(zip(problem.names, np.round(np.exp(t_best), 9)))}")
    for name, metric in (("Laplace covariance in u", in_u), ("Laplace covariance of t", of_t), ("... plus the ridge path", L @ L.T)):
        inverse = np.linalg.inv(np.linalg.cholesky(metric))
        w = np.linalg.eigvalsh(inverse @ draws @ inverse.T)
        print(f"{name:26s} eigenvalues of the draws' covariance in z {np.array2string(w, precision=3)}, "
              f"condition number {w.max() / w.min():.0f}")


if __name__ == "__main__":
    main()
