"""Work done once: one compilation per mesh (not per model), one factorisation per matrix
(forward, adjoint and Jacobian share it), and host caches that belong to their solver."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg

import diffeit as de
from diffeit import linear_solve

_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/backend_compile_duration")


@pytest.fixture
def compilations():
    """The trace and compile events JAX reports while the test runs."""
    events = []

    def listener(event: str, duration: float, **_kwargs) -> None:
        if event in _COMPILE_EVENTS:
            events.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    yield events
    jax.monitoring.unregister_event_duration_listener(listener)


def test_equal_meshes_and_protocols_compare_and_hash_by_content():
    first = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    second = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    assert first is not second and first == second and hash(first) == hash(second)
    assert first != de.mesh.disc(16, electrode_width=0.2, h=0.16)
    assert first != de.mesh.disc(16, electrode_width=0.25, h=0.15)  # other electrodes, other mesh
    moved = de.Mesh.from_arrays(first.nodes * 1.001, first.triangles, first.electrodes)
    assert moved != first
    assert de.protocol.adjacent(16) == de.protocol.adjacent(16)
    assert de.protocol.adjacent(16) != de.protocol.skip(16, 1)
    assert de.protocol.adjacent(16) != de.protocol.adjacent(16, measure_driven=True)


def test_a_second_model_on_an_equal_mesh_compiles_nothing(compilations):
    """Forward, Jacobian and one-step set-up of a model on a freshly generated, equal mesh reuse
    the first model's compiled functions: no trace, no compile."""

    def use(model):
        sigma = jnp.full(model.n_elements, 0.5)
        np.asarray(model.measure(sigma))
        np.asarray(model.jacobian(sigma))
        de.inverse.OneStep(model, "noser", 0.1).matrix.block_until_ready()

    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.17)
    use(de.ForwardModel(mesh, de.protocol.adjacent(16), 0.02))
    assert compilations  # the first model compiled: the listener hears compilations
    compilations.clear()
    again = de.mesh.disc(16, electrode_width=0.2, h=0.17)
    use(de.ForwardModel(again, de.protocol.adjacent(16), 0.03))  # contact impedance is a leaf
    assert compilations == []
    use(de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.18), de.protocol.adjacent(16), 0.02))
    assert compilations  # another mesh compiles anew


@pytest.mark.slow
def test_a_model_whose_readings_differ_shares_the_solves_compiled_programs(compilations):
    """`measure`, `potentials` and `jacobian` take the protocol's arrays as arguments: a model
    reading with other weights (a fitted readout) but as many readings compiles nothing, and
    reads its own weights (the readings of every electrode's potential, weighed)."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.17)
    plain = de.protocol.opposite(16)
    rng = np.random.default_rng(0)
    mixed = de.Protocol(plain.drive, (plain.measure + 0.1 * rng.normal(size=plain.measure.shape)).reshape(16, -1, 16))
    sigma = jnp.full(mesh.n_elements, 0.5)

    def use(model):
        return np.asarray(model.measure(sigma)), np.asarray(model.jacobian(sigma)), model.potentials(sigma)

    use(de.ForwardModel(mesh, plain, 0.02))
    first = use(de.ForwardModel(mesh, mixed, 0.02))
    compilations.clear()
    other = de.Protocol(plain.drive, (plain.measure - 0.1 * rng.normal(size=plain.measure.shape)).reshape(16, -1, 16))
    readings, jacobian, potentials = use(de.ForwardModel(mesh, other, 0.02))
    assert compilations == []
    every = potentials.electrode[other.drive_index]
    np.testing.assert_allclose(readings, np.sum(other.measure * every, axis=1), rtol=1e-12)
    assert not np.allclose(readings, first[0], rtol=1e-3)
    lower = np.asarray(de.ForwardModel(mesh, other, 0.02).measure(sigma * (1 - 1e-6 * np.eye(mesh.n_elements)[3])))
    np.testing.assert_allclose((readings - lower) / (0.5e-6), jacobian[:, 3], rtol=1e-4, atol=1e-9)


def test_dense_cholesky_factorises_once_for_the_forward_and_the_adjoint(small_disc, monkeypatch):
    """The gradient of the voltages is a forward and an adjoint solve with one factorisation
    between them (counted as traced), and it agrees with the host backend."""
    calls = []
    for name in ("factorise", "solve_factorised"):
        original = getattr(linear_solve.DenseCholesky, name)

        def counting(self, *args, _name=name, _original=original):
            calls.append(_name)
            return _original(self, *args)

        monkeypatch.setattr(linear_solve.DenseCholesky, name, counting)
    model = de.ForwardModel(small_disc, de.protocol.adjacent(16), 0.01, solver="dense_cholesky")
    sigma = jnp.linspace(0.5, 1.5, small_disc.n_elements)
    weights = jnp.asarray(np.random.default_rng(3).normal(size=model.n_measurements))

    def loss(s):
        return model.measure(s) @ weights

    jax.clear_caches()  # an equal model of an earlier test would otherwise spare the trace
    jax.make_jaxpr(jax.grad(loss))(sigma)
    assert calls == ["factorise", "solve_factorised", "solve_factorised"]
    host = de.ForwardModel(small_disc, de.protocol.adjacent(16), 0.01)
    np.testing.assert_allclose(jax.grad(loss)(sigma), jax.grad(lambda s: host.measure(s) @ weights)(sigma), rtol=1e-9)


def test_host_factorisations_belong_to_their_solver(monkeypatch):
    """Two solvers with different cache sizes keep separate caches: one's trimming does not
    evict the other's factorisations."""
    rng = np.random.default_rng(2)
    n = 20
    rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    near = np.abs(rows - cols) <= 1
    pattern, _ = linear_solve.SparsityPattern.from_entries(rows[near], cols[near], n)
    values = np.where(pattern.rows == pattern.cols, 4.0, -1.0)
    rhs = jnp.asarray(rng.normal(size=(n, 1)))
    keeper, trimmer = linear_solve.HostSparse(cache_size=4), linear_solve.HostSparse(cache_size=1)
    linear_solve.solve_spd(pattern, jnp.asarray(values), rhs, keeper)
    for scale in (2.0, 3.0, 5.0):
        linear_solve.solve_spd(pattern, jnp.asarray(scale * values), rhs, trimmer)
    factorisations = []
    original = scipy.sparse.linalg.splu
    monkeypatch.setattr(scipy.sparse.linalg, "splu", lambda *a, **k: factorisations.append(1) or original(*a, **k))
    linear_solve.solve_spd(pattern, jnp.asarray(values), rhs, keeper)
    assert factorisations == []  # still in the keeper's cache
    keeper.clear_cache()
    linear_solve.solve_spd(pattern, jnp.asarray(values), rhs, keeper)
    assert len(factorisations) == 2  # the ordering and the factorisation, made again


def test_a_model_pickles_with_an_empty_cache_and_reuses_the_compiled_functions(compilations):
    """Models travel to other processes (sweeps): a pickled model arrives equal in content,
    with an empty host cache of its own, and measures what the original measures."""
    import pickle

    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.3)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), 0.02)
    sigma = jnp.linspace(0.5, 1.5, mesh.n_elements)
    voltages = np.asarray(model.measure(sigma))
    copy = pickle.loads(pickle.dumps(model))
    assert copy.mesh == mesh and copy.mesh is not mesh and copy.protocol == model.protocol
    assert copy.solver == model.solver and copy.solver._cache is not model.solver._cache
    assert not copy.solver._cache.factors
    compilations.clear()
    np.testing.assert_array_equal(np.asarray(copy.measure(sigma)), voltages)
    assert compilations == []
