"""Bad input gets a ValueError naming the problem, never a silent NaN."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest


@pytest.mark.parametrize("method", ["measure", "jacobian", "potentials"])
def test_bad_conductivity_is_refused(small_model, method):
    call = getattr(small_model, method)
    n = small_model.n_elements
    good = np.ones(n)
    with pytest.raises(ValueError, match=rf"shape \({n - 1},\); expected \({n},\)"):
        call(good[:-1])
    with pytest.raises(ValueError, match=r"not finite \(NaN or inf\) at 1 element\(s\) \[3\]"):
        call(np.where(np.arange(n) == 3, np.nan, good))
    with pytest.raises(ValueError, match=r"not finite .* \[0, 7\]"):
        call(np.where(np.isin(np.arange(n), [0, 7]), np.inf, good))
    with pytest.raises(ValueError, match=r"must be positive .* \[5\]"):
        call(np.where(np.arange(n) == 5, 0.0, good))
    with pytest.raises(ValueError, match="must be positive"):
        call(-good)
    with pytest.raises(ValueError, match="shape"):
        call(np.ones((2, n)))


def test_bad_contact_impedance_is_refused(small_disc, small_model):
    import diffeit as de

    sigma = jnp.ones(small_model.n_elements)
    with pytest.raises(ValueError, match="contact_impedance must be finite and positive"):
        small_model.measure(sigma, 0.0)
    with pytest.raises(ValueError, match="contact_impedance must be finite and positive"):
        small_model.measure(sigma, jnp.full(16, jnp.nan))
    with pytest.raises(ValueError, match=r"expected a scalar or \(16,\)"):
        small_model.measure(sigma, jnp.ones(15))
    with pytest.raises(ValueError, match="contact_impedance"):
        de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance=-1.0)
    with pytest.raises(ValueError, match="drive_current"):
        de.ForwardModel(small_disc, de.protocol.adjacent(16), drive_current=0.0)


def test_traced_inputs_are_not_checked_but_still_work(small_model):
    """Under jit the values are unknown at trace time: only the shape is checked."""
    sigma = jnp.ones(small_model.n_elements)
    np.testing.assert_allclose(jax.jit(small_model.measure)(sigma), small_model.measure(sigma), rtol=1e-13)
    with pytest.raises(ValueError, match="expected"):
        jax.jit(small_model.measure)(sigma[:-1])
