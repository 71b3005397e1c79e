"""The differentiable sparse SPD solve and its backends."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg

import diffeit as de
import diffeit.linear_solve as linear_solve
from diffeit.results import RESULTS


def _laplacian_system(n: int = 30, seed: int = 0):
    """A random SPD matrix on a path-plus-chords pattern: its pattern and values."""
    rng = np.random.default_rng(seed)
    rows = np.concatenate([np.arange(n), np.arange(n - 1), np.arange(1, n), [0, 5], [5, 0]])
    cols = np.concatenate([np.arange(n), np.arange(1, n), np.arange(n - 1), [5, 0], [0, 5]])
    pattern, _slots = linear_solve.SparsityPattern.from_entries(rows, cols, n)
    weights = rng.uniform(0.5, 2.0, n - 1)
    dense = np.zeros((n, n))
    for i, w in enumerate(weights):
        dense[[i, i + 1], [i, i + 1]] += w
        dense[i, i + 1] -= w
        dense[i + 1, i] -= w
    dense[0, 5] = dense[5, 0] = -0.3
    dense[[0, 5], [0, 5]] += 0.3
    dense += np.diag(rng.uniform(0.1, 1.0, n))
    values = dense[pattern.rows, pattern.cols]
    return pattern, jnp.asarray(values), dense


def test_pattern_round_trip_and_matvec():
    pattern, values, dense = _laplacian_system()
    np.testing.assert_allclose(pattern.to_scipy(np.asarray(values)).toarray(), dense)
    x = np.random.default_rng(1).normal(size=(30, 3))
    np.testing.assert_allclose(pattern.matvec(values, jnp.asarray(x)), dense @ x, rtol=1e-13)


BACKENDS = [linear_solve.HostSparse(), linear_solve.DenseCholesky(), linear_solve.ConjugateGradient()]


@pytest.mark.parametrize("solver", BACKENDS, ids=lambda solver: type(solver).__name__)
def test_solve_matches_dense_solution_and_its_derivatives(solver):
    pattern, values, dense = _laplacian_system()
    rhs = jnp.asarray(np.random.default_rng(2).normal(size=(30, 4)))
    x = linear_solve.solve_spd(pattern, values, rhs, solver)
    np.testing.assert_allclose(x, np.linalg.solve(dense, rhs), rtol=1e-11)
    vector = linear_solve.solve_spd(pattern, values, rhs[:, 0], solver)
    np.testing.assert_allclose(vector, x[:, 0], rtol=1e-13)
    # d x / d values: reverse and forward mode against the dense formula -A^-1 dA x.
    tangent = jnp.asarray(np.random.default_rng(3).normal(size=pattern.nnz))
    tangent = 0.5 * (tangent + tangent[_transpose_slots(pattern)])  # a symmetric perturbation
    forward = jax.jvp(lambda v: linear_solve.solve_spd(pattern, v, rhs, solver), (values,), (tangent,))[1]
    perturbation = pattern.to_scipy(np.asarray(tangent)).toarray()
    np.testing.assert_allclose(forward, -np.linalg.solve(dense, perturbation @ np.asarray(x)), rtol=1e-10)
    reverse = jax.grad(lambda v: jnp.sum(linear_solve.solve_spd(pattern, v, rhs, solver)))(values)
    np.testing.assert_allclose(reverse @ tangent, forward.sum(), rtol=1e-10)


def _transpose_slots(pattern):
    position = {(r, c): i for i, (r, c) in enumerate(zip(pattern.rows, pattern.cols, strict=True))}
    return np.array([position[c, r] for r, c in zip(pattern.rows, pattern.cols, strict=True)])


@pytest.fixture
def counted_host_calls(monkeypatch):
    calls = []
    original = linear_solve._host_solve

    def counting(pattern, values, rhs, cache_size, cache):
        calls.append((values.shape, rhs.shape))
        return original(pattern, values, rhs, cache_size, cache)

    monkeypatch.setattr(linear_solve, "_host_solve", counting)
    return calls


def test_a_batch_of_right_hand_sides_is_one_host_call(counted_host_calls):
    pattern, values, dense = _laplacian_system()
    rhs = jnp.asarray(np.random.default_rng(4).normal(size=(7, 30, 2)))
    solve = jax.vmap(lambda b: linear_solve.solve_spd(pattern, values, b, linear_solve.HostSparse()))
    x = solve(rhs)
    np.testing.assert_allclose(x, np.linalg.solve(dense, np.asarray(rhs)), rtol=1e-11)
    assert len(counted_host_calls) == 1
    assert counted_host_calls[0] == ((1, pattern.nnz), (7, 30, 2))  # the matrix is not copied 7 times


def test_a_batch_of_matrices_is_one_host_call(counted_host_calls):
    pattern, values, dense = _laplacian_system()
    scales = jnp.array([1.0, 2.0, 5.0])
    rhs = jnp.ones((30, 1))
    x = jax.vmap(lambda s: linear_solve.solve_spd(pattern, s * values, rhs, linear_solve.HostSparse()))(scales)
    for s, xi in zip(scales, x, strict=True):
        np.testing.assert_allclose(xi, np.linalg.solve(float(s) * dense, np.ones((30, 1))), rtol=1e-11)
    assert len(counted_host_calls) == 1


def test_a_factorisation_is_reused_for_the_same_matrix(monkeypatch):
    pattern, values, dense = _laplacian_system(seed=5)
    solver = linear_solve.HostSparse()
    linear_solve.solve_spd(pattern, 3 * values, jnp.ones((30, 1)), solver)  # orders the pattern once
    factorisations = []
    original = scipy.sparse.linalg.splu

    def counting(*args, **kwargs):
        factorisations.append(kwargs["permc_spec"])
        return original(*args, **kwargs)

    monkeypatch.setattr(scipy.sparse.linalg, "splu", counting)
    first = linear_solve.solve_spd(pattern, values, jnp.ones((30, 1)), solver)
    second = linear_solve.solve_spd(pattern, values, 2 * jnp.ones((30, 1)), solver)
    np.testing.assert_allclose(second, 2 * first, rtol=1e-14)
    np.testing.assert_allclose(first, np.linalg.solve(dense, np.ones((30, 1))), rtol=1e-12)
    assert factorisations == ["NATURAL"]  # the fill-reducing order was computed once, before
    linear_solve.solve_spd(pattern, 1.5 * values, jnp.ones((30, 1)), solver)
    assert factorisations == ["NATURAL", "NATURAL"]


@pytest.mark.parametrize("solver", BACKENDS, ids=lambda solver: type(solver).__name__)
def test_backends_solve_batches_under_vmap(solver):
    pattern, values, dense = _laplacian_system(seed=6)
    rhs = jnp.asarray(np.random.default_rng(8).normal(size=(5, 30, 3)))
    scales = jnp.linspace(1.0, 3.0, 5)
    x = jax.jit(jax.vmap(lambda s, b: linear_solve.solve_spd(pattern, s * values, b, solver)))(scales, rhs)
    for s, b, xi in zip(scales, rhs, x, strict=True):
        np.testing.assert_allclose(xi, np.linalg.solve(float(s) * dense, np.asarray(b)), rtol=1e-10)


def test_conjugate_gradient_stops_each_column_at_its_tolerance():
    """A loose tolerance is honoured per column, and columns of a batch do not change each
    other's result (a converged column stops moving)."""
    pattern, values, _ = _laplacian_system(seed=9)
    rhs = jnp.asarray(np.random.default_rng(10).normal(size=(30, 2)))
    loose = linear_solve.ConjugateGradient(relative_tolerance=1e-4)
    together = linear_solve.solve_spd(pattern, values, rhs, loose)
    alone = linear_solve.solve_spd(pattern, values, rhs[:, :1], loose)
    np.testing.assert_allclose(together[:, :1], alone, rtol=1e-14)
    residual = linear_solve.relative_residual(pattern, values, together, rhs)
    assert np.all(residual <= 1e-4)
    assert np.all(residual > 1e-12)  # it did stop early: not solved to rounding error
    capped = linear_solve.ConjugateGradient(max_iterations=3, throw=False)
    assert np.all(linear_solve.relative_residual(pattern, values, capped.solve(pattern, values, rhs), rhs) > 1e-3)


def test_conjugate_gradient_reports_or_raises_when_it_stops_at_its_limit():
    """An unconverged solve raises by default (also under jit), and with throw=False carries
    the result code instead; a converged one reports success."""
    pattern, values, _ = _laplacian_system(seed=9)
    rhs = jnp.asarray(np.random.default_rng(10).normal(size=(30, 2)))
    with pytest.raises(Exception, match="did not reach its tolerance"):
        linear_solve.solve_spd(pattern, values, rhs, linear_solve.ConjugateGradient(max_iterations=3))
    # Under a plain jax.jit the run-time error surfaces where an output is read.
    capped = linear_solve.ConjugateGradient(max_iterations=3)
    jitted = jax.jit(lambda v: linear_solve.solve_spd(pattern, v, rhs, capped))
    with pytest.raises(Exception, match="did not reach its tolerance"):
        np.asarray(jitted(values))
    capped = linear_solve.ConjugateGradient(max_iterations=3, throw=False)
    _, result = linear_solve.solve_spd_with_result(pattern, values, rhs, capped)
    assert result == RESULTS.linear_solve_not_converged
    for backend in (linear_solve.ConjugateGradient(), linear_solve.HostSparse(), linear_solve.DenseCholesky()):
        x, result = linear_solve.solve_spd_with_result(pattern, values, rhs, backend)
        assert result == RESULTS.successful
        assert np.all(linear_solve.relative_residual(pattern, values, x, rhs) < 1e-10)


def test_the_forward_model_passes_the_solve_result_on(small_model, rough_conductivity):
    """measure raises for an unconverged conjugate-gradient solve; potentials with throw=False
    carries the code and the large residual."""
    capped = linear_solve.ConjugateGradient(max_iterations=5)
    strict = de.ForwardModel(small_model.mesh, small_model.protocol, solver=capped)
    with pytest.raises(Exception, match="did not reach its tolerance"):
        strict.measure(rough_conductivity)
    lenient = de.ForwardModel(
        small_model.mesh, small_model.protocol, solver=linear_solve.ConjugateGradient(max_iterations=5, throw=False)
    )
    potentials = lenient.potentials(rough_conductivity)
    assert potentials.result == RESULTS.linear_solve_not_converged
    assert np.all(potentials.relative_residual > 1e-4)
    assert small_model.potentials(rough_conductivity).result == RESULTS.successful


def test_backward_error_is_near_epsilon_for_a_direct_solve_and_not_for_a_wrong_one():
    pattern, values, _ = _laplacian_system(seed=11)
    rhs = jnp.asarray(np.random.default_rng(12).normal(size=(30, 2)))
    x = linear_solve.solve_spd(pattern, values, rhs, linear_solve.HostSparse())
    assert np.all(linear_solve.backward_error(pattern, values, x, rhs) < 1e-15)
    assert np.all(linear_solve.backward_error(pattern, values, 1.01 * x, rhs) > 1e-3)


@pytest.mark.parametrize("solver", BACKENDS[:2], ids=lambda solver: type(solver).__name__)
def test_a_singular_matrix_gives_nan_not_an_exception(solver):
    pattern, values, _ = _laplacian_system()
    x = linear_solve.solve_spd(pattern, jnp.zeros_like(values), jnp.ones((30, 1)), solver)
    assert np.all(np.isnan(x))


def test_non_symmetric_patterns_are_refused():
    with pytest.raises(ValueError, match="not symmetric"):
        linear_solve.SparsityPattern.from_entries(np.array([0, 1]), np.array([1, 1]), 2)


def test_an_unconverged_solve_raises_at_the_call_while_other_work_is_in_flight(small_model, rough_conductivity):
    """JAX dispatches asynchronously: while earlier work is still running, a compiled call
    returns before its run-time check has run, and under plain `jax.jit` the error surfaces only
    where an output is read (never, if none is). The eager entry points raise at the call all the
    same. Before they did, this failed in clean clones, where compiling left work in flight."""
    pattern, values, _ = _laplacian_system(seed=9)
    rhs = jnp.asarray(np.random.default_rng(10).normal(size=(30, 2)))
    capped = linear_solve.ConjugateGradient(max_iterations=3)
    strict = de.ForwardModel(
        small_model.mesh, small_model.protocol, solver=linear_solve.ConjugateGradient(max_iterations=5)
    )
    calls = {
        "solve_spd": lambda: linear_solve.solve_spd(pattern, values, rhs, capped),
        "measure": lambda: strict.measure(rough_conductivity),
        "potentials": lambda: strict.potentials(rough_conductivity),
        "jacobian": lambda: strict.jacobian(rough_conductivity),
    }
    busy = jnp.ones((1500, 1500))
    for name, call in calls.items():
        for attempt in ("compiling", "compiled"):
            in_flight = busy @ busy @ busy
            assert not in_flight.is_ready(), "the check needs work in flight"
            with pytest.raises(Exception, match="did not reach its tolerance"):
                call()
                pytest.fail(f"{name} ({attempt}) returned")
            in_flight.block_until_ready()


_FAILING_SOLVE = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", {cache!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
import diffeit as de
mesh = de.mesh.disc(16, electrode_width=0.2, h=0.3)
capped = de.linear_solve.ConjugateGradient(max_iterations=2)
model = de.ForwardModel(mesh, de.protocol.adjacent(16), solver=capped)
busy = jnp.ones((1000, 1000))
for _ in range(2):
    in_flight = busy @ busy
    try:
        model.measure(jnp.ones(mesh.n_elements))
    except Exception as error:
        assert "did not reach its tolerance" in str(error), error
    else:
        raise SystemExit("an unconverged solve did not raise")
print("raised")
"""


def test_an_unconverged_solve_raises_with_the_persistent_compilation_cache_on(tmp_path):
    """Users who turn on JAX's persistent compilation cache get the same errors: a program with
    run-time checks is never written to the cache (JAX keeps no programs with host callbacks),
    so a second, warm process compiles and checks again."""
    script = _FAILING_SOLVE.format(cache=str(tmp_path / "cache"))
    for process in ("cold", "warm"):
        run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
        assert run.returncode == 0 and run.stdout.strip() == "raised", (process, run.stdout, run.stderr[-2000:])
    assert any((tmp_path / "cache").iterdir()), "the cache was in use"
