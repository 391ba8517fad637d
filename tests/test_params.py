import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtissue as jt
from jaxtissue.params import FIELDS, moser_aiba, nondimensionalise, proliferation_prefactor


def test_every_field_documented_with_unit_and_default():
    p = jt.paper_parameters()
    names = set(p.as_dict())
    assert names == set(FIELDS)
    for name in ("k_c_max", "k_a", "k_m0", "o_m", "lumping_C", "E_s_kPa", "E_m0_kPa_per_ug_g"):
        assert name in FIELDS
    for info in FIELDS.values():
        assert info.unit and info.doc


def test_k_p_is_derived_from_k_c_max():
    p = jt.paper_parameters()
    k_p = float(proliferation_prefactor(p))
    assert k_p == pytest.approx(0.01279, rel=1e-3)  # docs/model.md §2
    # independent check: brute-force maximum of the Moser-Aiba factor
    o = np.linspace(1e-3, 1.0, 200001)
    g = o**5 / (0.45**5 + o**5) * np.exp(-14 * o)
    assert k_p == pytest.approx((1.24e-5 + 1e-5) / g.max(), rel=1e-8)
    # the net rate then changes sign at the anoxic (~0.177) and toxic (~0.468) levels
    kc = k_p * np.asarray(moser_aiba(o, 5.0, 0.45, 14.0)) - 1e-5
    crossings = o[np.nonzero(np.diff(np.sign(kc)))[0]]
    np.testing.assert_allclose(crossings, [0.177, 0.468], atol=2e-3)


def test_k_p_gradient_matches_finite_differences():
    p = jax.tree_util.tree_map(jnp.asarray, jt.paper_parameters())
    g = jax.grad(lambda q: proliferation_prefactor(q))(p)
    for name in ("k_c_max", "o_c", "k_i", "n_moser"):
        v = float(getattr(p, name))
        eps = 1e-6 * v
        fd = (
            proliferation_prefactor(p.replace(**{name: v + eps}))
            - proliferation_prefactor(p.replace(**{name: v - eps}))
        ) / (2 * eps)
        assert float(getattr(g, name)) == pytest.approx(float(fd), rel=1e-6)


@pytest.mark.parametrize(
    "name, value",
    [("k_a", -1e-5), ("D_o0", -1.0), ("o_m", 1.5), ("o_m", 0.0), ("thickness_mm", 0.0), ("nu_s", 0.5)],
)
def test_invalid_values_raise_naming_field_value_and_range(name, value):
    with pytest.raises(ValueError) as err:
        jt.paper_parameters(**{name: value})
    message = str(err.value)
    assert name in message and f"{value:g}" in message and "allowed range" in message


def test_unknown_name_suggests_the_closest():
    with pytest.raises(ValueError, match="did you mean 'k_c_max'"):
        jt.paper_parameters(k_cmax=1e-5)


def test_nondimensional_view_units():
    k = nondimensionalise(jt.paper_parameters())
    assert float(k.thickness_cm) == pytest.approx(0.1)
    assert float(k.length_cm) == pytest.approx(2.5)
