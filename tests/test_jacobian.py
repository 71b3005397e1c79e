"""The fast Jacobian, reverse- and forward-mode autodiff and finite differences agree."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de


def _relative(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max())


def test_fast_jacobian_equals_jacrev(small_model, rough_conductivity):
    fast = small_model.jacobian(rough_conductivity)
    assert fast.shape == (208, small_model.n_elements)
    reverse = jax.jacrev(small_model.measure)(rough_conductivity)
    forward = jax.jacfwd(small_model.measure)(rough_conductivity)
    assert _relative(fast, reverse) < 1e-9
    assert _relative(forward, reverse) < 1e-9


def test_jacobian_matches_central_differences_in_random_directions(small_model, rough_conductivity):
    jacobian = small_model.jacobian(rough_conductivity)
    rng = np.random.default_rng(7)
    for _ in range(3):
        direction = rng.normal(size=small_model.n_elements) * rough_conductivity
        step = 1e-4
        difference = (
            small_model.measure(rough_conductivity + step * direction)
            - small_model.measure(rough_conductivity - step * direction)
        ) / (2 * step)
        assert _relative(jacobian @ direction, difference) < 1e-6
        tangent = jax.jvp(small_model.measure, (rough_conductivity,), (direction,))[1]
        assert _relative(tangent, jacobian @ direction) < 1e-10


def test_gradient_of_a_scalar_loss_matches_finite_differences(small_model, rough_conductivity):
    target = small_model.measure(jnp.ones(small_model.n_elements))

    def loss(sigma):
        return jnp.sum((small_model.measure(sigma) - target) ** 2) / jnp.sum(target**2)

    gradient = jax.grad(loss)(rough_conductivity)
    np.testing.assert_allclose(
        gradient,
        2
        * small_model.jacobian(rough_conductivity).T
        @ (small_model.measure(rough_conductivity) - target)
        / jnp.sum(target**2),
        rtol=1e-9,
        atol=1e-12 * np.abs(gradient).max(),
    )
    rng = np.random.default_rng(11)
    for _ in range(3):
        direction = rng.normal(size=small_model.n_elements)
        step = 1e-5
        difference = (loss(rough_conductivity + step * direction) - loss(rough_conductivity - step * direction)) / (
            2 * step
        )
        np.testing.assert_allclose(gradient @ direction, difference, rtol=1e-6)


def test_jacobian_works_under_jit_and_vmap(small_model, rough_conductivity):
    expected = small_model.jacobian(rough_conductivity)
    assert _relative(jax.jit(small_model.jacobian)(rough_conductivity), expected) < 1e-12
    batched = jax.vmap(small_model.jacobian)(jnp.stack([rough_conductivity, 3 * rough_conductivity]))
    assert _relative(batched[0], expected) < 1e-12
    assert _relative(batched[1], small_model.jacobian(3 * rough_conductivity)) < 1e-12


@pytest.mark.slow
def test_derivatives_with_respect_to_contact_impedance(small_model, rough_conductivity):
    z = jnp.linspace(0.005, 0.05, 16)

    def measure(z):
        return small_model.measure(rough_conductivity, z)

    reverse = jax.jacrev(measure)(z)
    forward = jax.jacfwd(measure)(z)
    assert reverse.shape == (208, 16)
    assert _relative(forward, reverse) < 1e-9
    step = 1e-6
    for l in (0, 5, 15):
        bump = jnp.zeros(16).at[l].set(step * z[l])
        difference = (measure(z + bump) - measure(z - bump)) / (2 * step * z[l])
        assert _relative(reverse[:, l], difference) < 1e-6
    scalar = jax.grad(lambda z: jnp.sum(small_model.measure(rough_conductivity, z) ** 2))(0.02)
    difference = (
        jnp.sum(small_model.measure(rough_conductivity, 0.02 * (1 + 1e-6)) ** 2)
        - jnp.sum(small_model.measure(rough_conductivity, 0.02 * (1 - 1e-6)) ** 2)
    ) / (2 * 0.02e-6)
    np.testing.assert_allclose(scalar, difference, rtol=1e-6)


def test_gradient_through_the_model_as_a_pytree(small_model, rough_conductivity):
    """The model's contact impedance is its leaf: grad with respect to the model reaches it."""
    gradient = jax.grad(lambda model: jnp.sum(model.measure(rough_conductivity)))(small_model)
    expected = jax.grad(lambda z: jnp.sum(small_model.measure(rough_conductivity, z)))(small_model.contact_impedance)
    np.testing.assert_allclose(gradient.contact_impedance, expected, rtol=1e-12)


def test_fast_jacobian_for_a_general_protocol(small_disc, rough_conductivity):
    """Opposite drives, an arbitrary current pattern, and single-ended readings (weights that do
    not sum to zero: they read against the mean electrode potential)."""
    eye = np.eye(16)
    drive = np.stack([eye[8] - eye[0], eye[12] - eye[4], np.cos(2 * np.pi * np.arange(16) / 16)])
    measure = [eye[[1, 2, 3]], eye[[5, 9]] - 0.5 * eye[[6, 10]], eye[[0, 7, 15]]]
    model = de.ForwardModel(small_disc, de.Protocol(drive, measure), contact_impedance=0.02)
    fast = model.jacobian(rough_conductivity)
    assert fast.shape == (8, small_disc.n_elements)
    assert _relative(fast, jax.jacrev(model.measure)(rough_conductivity)) < 1e-9
    direction = np.random.default_rng(3).normal(size=small_disc.n_elements) * rough_conductivity
    difference = (
        model.measure(rough_conductivity + 1e-4 * direction) - model.measure(rough_conductivity - 1e-4 * direction)
    ) / 2e-4
    assert _relative(fast @ direction, difference) < 1e-6


def test_jacobian_in_log_conductivity(small_model, rough_conductivity):
    fast = small_model.jacobian(rough_conductivity, wrt="log_conductivity")
    reverse = jax.jacrev(lambda log_sigma: small_model.measure(jnp.exp(log_sigma)))(jnp.log(rough_conductivity))
    assert _relative(fast, reverse) < 1e-9
    assert _relative(fast, small_model.jacobian(rough_conductivity) * rough_conductivity) < 1e-14


def test_jacobian_in_contact_impedance_per_electrode(small_disc, rough_conductivity):
    z = jnp.asarray(np.exp(np.random.default_rng(11).normal(np.log(0.02), 0.5, 16)))
    model = de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance=z)
    fast = model.jacobian(rough_conductivity, wrt="contact_impedance")
    assert fast.shape == (208, 16)
    reverse = jax.jacrev(lambda zz: model.measure(rough_conductivity, zz))(z)
    assert _relative(fast, reverse) < 1e-9
    for electrode in (0, 7, 15):  # 15 carries the ground node: nothing special about it
        step = 1e-5 * z[electrode]
        plus, minus = z.at[electrode].add(step), z.at[electrode].add(-step)
        difference = (model.measure(rough_conductivity, plus) - model.measure(rough_conductivity, minus)) / (2 * step)
        assert _relative(fast[:, electrode], difference) < 1e-7


def test_wrt_is_checked(small_model, rough_conductivity):
    with pytest.raises(ValueError, match="wrt must be one of"):
        small_model.jacobian(rough_conductivity, wrt="sigma")


@pytest.mark.parametrize("measure_driven", [False, True], ids=["adjacent", "driven"])
def test_readings_and_jacobian_together_equal_measure_and_jacobian(small_disc, rough_conductivity, measure_driven):
    """`measure_and_jacobian` takes the readings from the Jacobian's solves: the same readings
    and Jacobian as `measure` and `jacobian`, to rounding, with per-electrode contacts."""
    protocol = de.protocol.adjacent(16, measure_driven=measure_driven)
    contact = 0.01 * np.exp(np.random.default_rng(2).normal(0, 0.3, 16))
    model = de.ForwardModel(small_disc, protocol, contact_impedance=contact)
    readings, jacobian = model.measure_and_jacobian(rough_conductivity)
    expected = np.asarray(model.measure(rough_conductivity))
    assert _relative(np.asarray(readings), expected) < 1e-12
    assert _relative(np.asarray(jacobian), np.asarray(model.jacobian(rough_conductivity))) < 1e-12
