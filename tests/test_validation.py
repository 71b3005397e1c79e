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


@pytest.mark.parametrize("method", ["measure", "jacobian"])
def test_traced_inputs_are_checked_at_run_time(small_model, method):
    """Under jit or vmap the values are unknown at trace time: shapes raise ValueError then,
    values raise at run time instead of giving NaN or solving an indefinite system."""
    sigma = jnp.ones(small_model.n_elements)
    call = jax.jit(getattr(small_model, method))
    np.testing.assert_allclose(call(sigma), getattr(small_model, method)(sigma), rtol=1e-13)
    with pytest.raises(ValueError, match="expected"):
        call(sigma[:-1])
    for bad in (sigma.at[3].set(jnp.nan), sigma.at[3].set(-1.0), sigma.at[0].set(0.0)):
        with pytest.raises(Exception, match="conductivity must be finite and positive"):
            call(bad).block_until_ready()
    with pytest.raises(Exception, match="conductivity must be finite and positive"):
        jax.vmap(getattr(small_model, method))(jnp.stack([sigma, -sigma])).block_until_ready()
    with pytest.raises(Exception, match="contact_impedance must be finite and positive"):
        jax.jit(lambda z: getattr(small_model, method)(sigma, z))(-0.01).block_until_ready()
