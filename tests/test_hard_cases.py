"""Hard cases stay numerically sound: extreme contrast, extreme contact impedance, thin and
badly shaped elements. Results are finite, the direct backends are backward stable (the
componentwise backward error is near machine epsilon) and the residual is returned."""

import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de

DIRECT = ["host_sparse", "dense_cholesky"]


def _relative(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def _checked(model: de.ForwardModel, conductivity: jnp.ndarray, *, direct: bool) -> de.Potentials:
    potentials = model.potentials(conductivity)
    assert potentials.relative_residual.shape == potentials.backward_error.shape == (model.protocol.n_drives,)
    assert np.all(np.isfinite(potentials.nodal)) and np.all(np.isfinite(potentials.electrode))
    if direct:
        # Measured at most 5e-12 (SuperLU without pivoting at contrast 1e6), 3e-16 elsewhere.
        assert np.all(potentials.backward_error < 1e-10)
        assert np.all(potentials.relative_residual < 1e-6)
    else:
        assert np.all(potentials.relative_residual < 1e-8)
    return potentials


@pytest.fixture(scope="module")
def checkerboard(small_disc):
    """Conductivity 1 or 1e6 S/sq at random per element: contrast 1e6 between neighbours."""
    return jnp.asarray(np.where(np.random.default_rng(0).random(small_disc.n_elements) < 0.5, 1.0, 1e6))


@pytest.mark.parametrize("contact_impedance", [1e-9, 1e-2, 1e3])
def test_contrast_of_a_million_between_neighbours(small_disc, checkerboard, contact_impedance):
    voltages = {}
    for solver in [*DIRECT, "conjugate_gradient"]:
        model = de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance, solver=solver)
        _checked(model, checkerboard, direct=solver in DIRECT)
        voltages[solver] = model.measure(checkerboard)
    # The two direct backends agree far beyond what the conditioning alone would promise.
    assert _relative(voltages["dense_cholesky"], voltages["host_sparse"]) < 1e-8
    assert _relative(voltages["conjugate_gradient"], voltages["host_sparse"]) < 1e-6


@pytest.mark.parametrize("solver", DIRECT)
def test_contact_impedance_from_1e_9_to_1e3_reaches_its_limits(small_disc, rough_conductivity, solver):
    """Voltages are finite over twelve decades of z and settle to the two limits: the shunt
    limit (z -> 0: electrodes equipotential with the sheet under them) and the uniform
    current density limit (z -> oo: readings no longer depend on z)."""
    voltages = {}
    for z in [1e-9, 1e-8, 1e-4, 1e-2, 1.0, 1e2, 1e3, 1e4]:
        model = de.ForwardModel(small_disc, de.protocol.adjacent(16), z, solver=solver)
        _checked(model, rough_conductivity, direct=True)
        voltages[z] = model.measure(rough_conductivity)
    # Measured: 1.8e-7 and 4.6e-6 on this mesh.
    assert _relative(voltages[1e-9], voltages[1e-8]) < 1e-6
    assert _relative(voltages[1e3], voltages[1e4]) < 1e-4
    assert _relative(voltages[1e-2], voltages[1e-9]) > 1e-3  # the physics did change in between


def _thin_column_grid(thin: float = 1e-5) -> de.Mesh:
    """The unit square on a 17 x 17 grid with one extra column and row of width `thin`:
    triangles with aspect ratios near 1/(16 thin) and angles near 16 thin radians."""
    xs = np.sort(np.append(np.linspace(0.0, 1.0, 17), 0.5 + thin))
    ys = np.sort(np.append(np.linspace(0.0, 1.0, 17), 0.25 + thin))
    index = np.arange(len(xs) * len(ys)).reshape(len(xs), len(ys))
    nodes = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    a, b, c, d = (index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel())
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    starts = (1, 5, 10, 14)  # four electrodes of two grid steps on every side
    electrodes = (
        [index[s : s + 2, 0] for s in starts]
        + [index[-1, s : s + 2] for s in starts]
        + [index[s : s + 2, -1] for s in starts[::-1]]
        + [index[0, s : s + 2] for s in starts[::-1]]
    )
    return de.Mesh.from_arrays(nodes, triangles, electrodes=electrodes)


def _thin_strip() -> de.Mesh:
    """A 1 x 0.001 strip: every element has an aspect ratio near 1000."""
    square = de.mesh.rectangle(1.0, 1.0, 16, h=0.1)
    return de.Mesh.from_arrays(square.nodes * [1.0, 1e-3], square.triangles, electrodes=list(square.electrodes))


@pytest.mark.slow
@pytest.mark.parametrize("build", [_thin_column_grid, _thin_strip])
def test_thin_and_badly_shaped_elements(build):
    mesh = build()
    sides = np.linalg.norm(np.diff(mesh.nodes[mesh.triangles[:, [0, 1, 2, 0]]], axis=1), axis=2)
    assert np.max(sides.max(axis=1) ** 2 / mesh.element_areas) > 1e3  # badly shaped indeed
    conductivity = jnp.asarray(np.exp(np.random.default_rng(1).normal(0.0, 0.5, mesh.n_elements)))
    voltages = {}
    for solver in [*DIRECT, "conjugate_gradient"]:
        model = de.ForwardModel(mesh, de.protocol.adjacent(16), 0.01, solver=solver)
        _checked(model, conductivity, direct=solver in DIRECT)
        voltages[solver] = model.measure(conductivity)
    assert _relative(voltages["dense_cholesky"], voltages["host_sparse"]) < 1e-10
    assert _relative(voltages["conjugate_gradient"], voltages["host_sparse"]) < 1e-8
