"""diffeit.fit's one optimisation loop (`minimise`): the minimum of a badly scaled quadratic with
and without units, and each result code on an objective made to produce it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffeit.fit._optimise import minimise
from diffeit.results import RESULTS

jax.config.update("jax_enable_x64", True)

# A quadratic whose curvatures differ by 1e6, its minimum away from the start in both unknowns.
CURVATURES = {"a": jnp.array([1e3, 1.0]), "b": jnp.array(1e-3)}
CENTRES = {"a": jnp.array([0.3, -2.0]), "b": jnp.array(5.0)}


def quadratic(y):
    return sum(0.5 * jnp.sum(CURVATURES[k] * (y[k] - CENTRES[k]) ** 2) for k in y)


START = {"a": jnp.zeros(2), "b": jnp.array(0.0)}


def test_units_precondition_a_badly_scaled_quadratic():
    units = jax.tree_util.tree_map(lambda c: 1 / jnp.sqrt(c), CURVATURES)
    found = minimise(quadratic, START, units=units, rtol=0.0, atol=1e-20, progress=False)
    assert found.result == RESULTS.successful
    for name in CENTRES:
        np.testing.assert_allclose(found.value[name], CENTRES[name], rtol=1e-6, atol=1e-8)
    # In the units' space the quadratic is round: L-BFGS needs only a few steps.
    assert len(found.objective) - 1 <= 15
    assert np.all(np.diff(found.objective) <= 0)
    assert found.objective[0] == pytest.approx(float(quadratic(START)))


def test_on_step_sees_the_start_and_every_accepted_step():
    """`on_step` gets the minimisation so far, unfinished, at the start and after every accepted
    step: the histories are the final one's beginnings, the last value the minimiser."""
    units = jax.tree_util.tree_map(lambda c: 1 / jnp.sqrt(c), CURVATURES)
    seen = []
    found = minimise(quadratic, START, units=units, rtol=0.0, atol=1e-20, progress=False, on_step=seen.append)
    assert len(seen) == len(found.objective)
    for steps, so_far in enumerate(seen):
        assert so_far.result == RESULTS.max_iterations_reached
        np.testing.assert_array_equal(so_far.objective, found.objective[: steps + 1])
        np.testing.assert_array_equal(so_far.gradient_norm, found.gradient_norm[: steps + 1])
        assert float(quadratic(so_far.value)) == pytest.approx(so_far.objective[-1], rel=1e-12, abs=1e-15)
    for name in CENTRES:
        np.testing.assert_array_equal(seen[-1].value[name], found.value[name])


def test_without_units_the_same_minimum_takes_many_more_steps():
    found = minimise(quadratic, START, max_steps=3000, rtol=0.0, atol=1e-20, progress=False)
    assert found.result == RESULTS.successful
    np.testing.assert_allclose(found.value["b"], CENTRES["b"], rtol=1e-4)
    assert len(found.objective) - 1 > 15


def test_a_step_cap_is_reported():
    found = minimise(quadratic, START, max_steps=30, progress=False)
    assert found.result == RESULTS.max_iterations_reached
    assert found.objective[-1] < found.objective[0]


def test_a_line_search_that_finds_no_lower_point_is_a_stall_not_a_minimum():
    """The objective jumps up at the start along its own gradient: every trial step is
    rejected, which optimistix's own test would end as converged (its step shrank to nothing)."""

    def jump(y):
        return jnp.sum(y) + jnp.where(jnp.sum(y) < 1.0, 10.0, 0.0)

    found = minimise(jump, jnp.array([0.5, 0.5]), max_steps=200, progress=False)
    assert found.result == RESULTS.stalled
    np.testing.assert_array_equal(found.value, [0.5, 0.5])
    assert len(found.objective) == 1


def test_a_nonfinite_start_is_reported_at_once():
    found = minimise(lambda y: jnp.sum(jnp.sqrt(jnp.abs(y))), jnp.zeros(2), progress=False)
    assert found.result == RESULTS.nonfinite
    assert len(found.objective) == 1 and not np.isfinite(found.gradient_norm[0])


def test_negative_step_cap_is_refused():
    with pytest.raises(ValueError, match="max_steps"):
        minimise(quadratic, START, max_steps=-1, progress=False)
