"""The solver backends agree with each other, under every JAX transformation; the point
electrode model agrees with pyEIT's."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pyeit.eit import protocol as pyeit_protocol
from pyeit.eit.fem import EITForward
from pyeit.mesh import PyEITMesh

import diffeit as de
from diffeit.linear_solve import ConjugateGradient, DenseCholesky, HostSparse


def _relative(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


@pytest.fixture(scope="module")
def contact_impedance():
    """Seeded, different on every electrode (ohm m)."""
    return jnp.asarray(np.exp(np.random.default_rng(5).normal(np.log(0.01), 0.3, 16)))


@pytest.fixture(scope="module", params=["dense_cholesky", "conjugate_gradient"])
def backend_pair(request, small_disc, contact_impedance):
    """(a model on the named JAX backend, the same model on the host sparse backend)."""
    protocol = de.protocol.adjacent(16)
    return (
        de.ForwardModel(small_disc, protocol, contact_impedance, solver=request.param),
        de.ForwardModel(small_disc, protocol, contact_impedance, solver="host_sparse"),
    )


@pytest.mark.slow
def test_backends_agree_on_voltages_potentials_and_jacobians(backend_pair, rough_conductivity):
    model, reference = backend_pair
    assert _relative(model.measure(rough_conductivity), reference.measure(rough_conductivity)) < 1e-9
    ours, theirs = model.potentials(rough_conductivity), reference.potentials(rough_conductivity)
    assert _relative(ours.nodal, theirs.nodal) < 1e-9
    assert np.all(ours.relative_residual < 1e-10)
    for wrt in ("conductivity", "log_conductivity", "contact_impedance"):
        assert (
            _relative(model.jacobian(rough_conductivity, wrt=wrt), reference.jacobian(rough_conductivity, wrt=wrt))
            < 1e-9
        )


@pytest.mark.slow
def test_backends_work_under_jit_vmap_jvp_and_jacrev(backend_pair, rough_conductivity, contact_impedance):
    model, reference = backend_pair
    batch = jnp.stack([rough_conductivity, rough_conductivity**2, jnp.sqrt(rough_conductivity)])
    batched = jax.jit(jax.vmap(model.measure))(batch)
    for sigma, voltages in zip(batch, batched, strict=True):
        assert _relative(voltages, reference.measure(sigma)) < 1e-9
    direction = jnp.asarray(np.random.default_rng(3).normal(size=model.n_elements))
    tangent = jax.jvp(model.measure, (rough_conductivity,), (direction,))[1]
    assert _relative(tangent, reference.jacobian(rough_conductivity) @ direction) < 1e-9
    # Reverse mode on every 13th reading (one of each drive's): each row is an adjoint solve, and
    # the conjugate-gradient backend's 208 of them take seconds where 16 show the same.
    rows = slice(None, None, 13)
    reverse = jax.jacrev(lambda sigma: model.measure(sigma)[rows])(rough_conductivity)
    assert _relative(reverse, reference.jacobian(rough_conductivity)[rows]) < 1e-9
    in_z = jax.jacrev(lambda z: model.measure(rough_conductivity, z)[rows])(contact_impedance)
    assert _relative(in_z, reference.jacobian(rough_conductivity, wrt="contact_impedance")[rows]) < 1e-9


_GAUSS_NEWTON_ON_A_BATCH = """
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import diffeit as de
mesh = de.mesh.disc(16, electrode_width=0.2, h=0.12)
change = -0.3 * de.mesh.disc_fraction(mesh, (0.5, 0.0), 0.2)
images = []
for solver in ("dense_cholesky", "host_sparse"):
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), 0.01, solver=solver)
    reference = np.asarray(model.measure(np.full(mesh.n_elements, 0.01)))
    touched = np.asarray(model.measure(0.01 * (1 + change)))
    noise = np.random.default_rng(0).normal(0, 1e-3 * np.abs(reference).max(), (4, reference.size))
    solver = de.inverse.GaussNewton(model, "laplace", 0.05, background=0.01, max_iterations=3)
    solution = solver.solve(touched + noise - reference, throw=False)
    images.append(np.asarray(solution.value))
print(np.abs(images[0] - images[1]).max() / np.abs(images[1]).max())
"""


def test_gauss_newton_on_a_batch_finishes_on_dense_cholesky_and_agrees():
    """Gauss-Newton on 4 frames (one vmapped call of voltages and Jacobians) on the dense
    Cholesky backend: jaxlib's batched LAPACK Cholesky on CPU waited for its own thread pool for
    ever there (2 cores); it now runs one matrix at a time. In a fresh process, so that a hang
    fails this test (after 5 minutes; it takes seconds) instead of stalling the suite."""
    run = subprocess.run([sys.executable, "-c", _GAUSS_NEWTON_ON_A_BATCH], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert float(run.stdout.split()[-1]) < 1e-8


def test_a_backend_is_chosen_by_name_or_instance(small_disc):
    protocol = de.protocol.adjacent(16)
    assert isinstance(de.ForwardModel(small_disc, protocol).solver, HostSparse)
    assert isinstance(de.ForwardModel(small_disc, protocol, solver="dense_cholesky").solver, DenseCholesky)
    loose = ConjugateGradient(relative_tolerance=1e-6)
    assert de.ForwardModel(small_disc, protocol, solver=loose).solver is loose
    with pytest.raises(ValueError, match="unknown solver 'cholmod'"):
        de.ForwardModel(small_disc, protocol, solver="cholmod")
    with pytest.raises(ValueError, match="solver must be"):
        de.ForwardModel(small_disc, protocol, solver=np.linalg.solve)
    with pytest.raises(ValueError, match="electrode_model must be"):
        de.ForwardModel(small_disc, protocol, electrode_model="gap")


def _pyeit_forward(mesh: de.Mesh, electrode_nodes: np.ndarray, conductivity: np.ndarray) -> np.ndarray:
    """pyEIT 1.2.4's point-electrode voltages for the adjacent protocol (1 A drive) on our mesh."""
    pyeit_mesh = PyEITMesh(
        node=mesh.nodes, element=mesh.triangles, perm=conductivity, el_pos=electrode_nodes, ref_node=0
    )
    forward = EITForward(pyeit_mesh, pyeit_protocol.create(16, dist_exc=1, step_meas=1, parser_meas="std"))
    return forward.solve_eit(perm=conductivity)


@pytest.mark.parametrize("solver", ["host_sparse", pytest.param("dense_cholesky", marks=pytest.mark.slow)])
def test_point_electrodes_agree_with_pyeit_on_the_same_mesh(small_disc, rough_conductivity, solver):
    """pyEIT's adjacent frames equal diffeit's value for value (its drive and reading signs
    are both flipped, see `diffeit.protocol.from_pyeit`); pyEIT drives 1 A."""
    model = de.ForwardModel(small_disc, de.protocol.adjacent(16), electrode_model="point", solver=solver)
    ours = model.measure(rough_conductivity) / model.drive_current
    theirs = _pyeit_forward(small_disc, model.system.electrode_nodes, np.asarray(rough_conductivity))
    assert _relative(ours, theirs) < 1e-10
    # The point electrodes sit at the centres of the complete model's electrodes.
    for node, chain in zip(model.system.electrode_nodes, small_disc.electrodes, strict=True):
        assert node in chain[1:-1]


def test_point_electrode_jacobians(small_disc, rough_conductivity):
    model = de.ForwardModel(small_disc, de.protocol.adjacent(16), electrode_model="point")
    assert _relative(model.jacobian(rough_conductivity), jax.jacrev(model.measure)(rough_conductivity)) < 1e-10
    assert np.all(model.jacobian(rough_conductivity, wrt="contact_impedance") == 0)
    # The contact impedance plays no part in the point model.
    np.testing.assert_array_equal(model.measure(rough_conductivity, 5.0), model.measure(rough_conductivity))


@pytest.mark.slow
def test_point_and_complete_electrodes_converge_as_electrodes_shrink():
    """Narrow electrodes with a small contact impedance behave like points, away from the
    driven electrodes (whose readings the adjacent protocol skips): the complete model's
    voltages approach the point model's as the electrode width shrinks."""
    errors = []
    for width in (0.2, 0.05):
        mesh = de.mesh.disc(16, electrode_width=width, h=0.15, electrode_h=width / 2)
        point = de.ForwardModel(mesh, de.protocol.adjacent(16), electrode_model="point")
        complete = de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=1e-6)
        sigma = jnp.ones(mesh.n_elements)
        errors.append(_relative(complete.measure(sigma), point.measure(sigma)))
    # Measured: 0.15 at width 0.2, 0.008 at 0.05: second order in the width.
    assert errors[1] < 0.1 * errors[0]
    assert errors[1] < 0.02
