"""Electrodes moved along the boundary (`ForwardModel(electrode_shift=...)`): a shift that moves
an electrode's ends onto other nodes gives the model of the mesh whose electrodes are those
nodes, exactly; its derivative agrees with finite differences, and the adjoint Jacobian
(`jacobian(wrt="electrode_shift")`) with forward differentiation through the solves; bad shifts
are refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de

PROTOCOL = de.protocol.adjacent(16)


@pytest.fixture(scope="module")
def mesh():
    return de.mesh.disc(16, h=0.12)


def _arc(mesh, a, b):
    return float(np.linalg.norm(mesh.nodes[a] - mesh.nodes[b]))


def _moved_mesh(mesh):
    """The same triangulation with electrode 2 one boundary node longer at its start, electrode 5
    one node later at both ends, electrode 9 one node shorter at its end; and those shifts, m."""
    following = dict(mesh.boundary_edges.tolist())
    preceding = {b: a for a, b in mesh.boundary_edges.tolist()}
    chains = [list(map(int, chain)) for chain in mesh.electrodes]
    shift = np.zeros((16, 2))
    before = preceding[chains[2][0]]
    shift[2, 0] = -_arc(mesh, before, chains[2][0])
    chains[2] = [before, *chains[2]]
    after = following[chains[5][-1]]
    shift[5] = _arc(mesh, chains[5][0], chains[5][1]), _arc(mesh, chains[5][-1], after)
    chains[5] = [*chains[5][1:], after]
    shift[9, 1] = -_arc(mesh, chains[9][-2], chains[9][-1])
    chains[9] = chains[9][:-1]
    return de.Mesh.from_arrays(mesh.nodes, mesh.triangles, chains), shift


def test_a_shift_onto_other_nodes_is_the_mesh_with_those_electrodes(mesh):
    moved, shift = _moved_mesh(mesh)
    conductivity = np.random.default_rng(0).uniform(0.5, 2.0, mesh.n_elements)
    z = np.linspace(0.005, 0.05, 16)
    expected = de.ForwardModel(moved, PROTOCOL, z)
    shifted = de.ForwardModel(mesh, PROTOCOL, z, electrode_shift=shift)
    scale = np.abs(expected.measure(conductivity)).max()
    np.testing.assert_allclose(shifted.measure(conductivity), expected.measure(conductivity), atol=1e-12 * scale)
    for wrt in ("conductivity", "contact_impedance"):
        reference = expected.jacobian(conductivity, wrt=wrt)
        np.testing.assert_allclose(
            shifted.jacobian(conductivity, wrt=wrt), reference, atol=1e-11 * np.abs(reference).max()
        )
    # No shift within a margin is the mesh's model.
    unmoved = de.ForwardModel(mesh, PROTOCOL, z, electrode_shift=np.zeros(16), electrode_margin=0.05)
    np.testing.assert_allclose(
        unmoved.measure(conductivity), de.ForwardModel(mesh, PROTOCOL, z).measure(conductivity), atol=1e-12 * scale
    )


def test_the_derivative_in_the_shift_agrees_with_finite_differences(mesh):
    """At zero (every end on a node, where the covered edge changes) and between nodes."""
    model = de.ForwardModel(mesh, PROTOCOL, 0.02, electrode_shift=np.zeros(16), electrode_margin=0.04)
    conductivity = jnp.asarray(np.random.default_rng(1).uniform(0.5, 2.0, mesh.n_elements))

    def voltages(shift):
        return eqx.tree_at(lambda m: m.electrode_shift, model, shift).measure(conductivity)

    for start in (np.zeros((16, 2)), np.random.default_rng(2).uniform(-0.03, 0.03, (16, 2))):
        derivative = jax.jacfwd(voltages)(jnp.asarray(start))
        step = 1e-6
        for electrode, end in [(0, 0), (4, 1), (11, 0), (15, 1)]:
            forward = voltages(jnp.asarray(start).at[electrode, end].add(step))
            backward = voltages(jnp.asarray(start).at[electrode, end].add(-step))
            difference = (forward - backward) / (2 * step)
            np.testing.assert_allclose(derivative[:, electrode, end], difference, atol=1e-4 * np.abs(difference).max())


def test_the_adjoint_jacobian_in_the_shift_is_forward_differentiation_through_the_solves(mesh):
    """At zero and between nodes, with a contact impedance per electrode (the 1/z of each
    electrode's terms), on the adjacent protocol and on one reading every electrode."""
    conductivity = jnp.asarray(np.random.default_rng(3).uniform(0.5, 2.0, mesh.n_elements))
    z = np.linspace(0.005, 0.05, 16)
    every = de.Protocol(np.eye(16)[:1] - np.eye(16)[8:9], [np.eye(16) - 1 / 16])
    for protocol in (PROTOCOL, every):
        for start in (np.zeros((16, 2)), np.random.default_rng(4).uniform(-0.03, 0.03, (16, 2))):
            model = de.ForwardModel(mesh, protocol, z, electrode_shift=start, electrode_margin=0.04)
            expected = jax.jacfwd(
                lambda shift, model=model: eqx.tree_at(lambda m: m.electrode_shift, model, shift).measure(conductivity)
            )(model.electrode_shift)
            adjoint = model.jacobian(conductivity, wrt="electrode_shift")
            assert adjoint.shape == (protocol.n_measurements, 16, 2)
            np.testing.assert_allclose(adjoint, expected, atol=1e-11 * np.abs(expected).max())
    # Lengthening the electrode the current enters by, at either end, lowers the resistance it
    # meets: its potential falls.
    model = de.ForwardModel(mesh, every, z, electrode_margin=0.04)
    voltages, adjoint = model.measure(conductivity), model.jacobian(conductivity, wrt="electrode_shift")
    assert voltages[0] > 0 and adjoint[0, 0, 0] > 0 and adjoint[0, 0, 1] < 0


def test_the_shift_jacobian_of_a_model_whose_electrodes_may_not_move_is_refused(mesh):
    model = de.ForwardModel(mesh, PROTOCOL, 0.02)
    with pytest.raises(ValueError, match="electrodes may move"):
        model.jacobian(jnp.ones(mesh.n_elements), wrt="electrode_shift")


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"electrode_shift": np.zeros(15)}, "electrode_shift has shape"),
        ({"electrode_shift": np.full(16, 0.1), "electrode_margin": 0.05}, "further than electrode_margin"),
        ({"electrode_shift": np.tile([0.05, -0.2], (16, 1))}, "no length"),
        ({"electrode_shift": np.full(16, np.nan), "electrode_margin": 0.05}, "not finite"),
        ({"electrode_shift": np.full(16, np.nan)}, "electrode_shift is not finite"),
        ({"electrode_shift": np.zeros(16), "electrode_model": "point"}, "complete electrode model"),
        ({"electrode_margin": -1.0}, "electrode_margin must be"),
    ],
)
def test_bad_shifts_are_refused_by_name(mesh, options, message):
    with pytest.raises(ValueError, match=message):
        de.ForwardModel(mesh, PROTOCOL, 0.02, **options)


def test_a_replaced_model_keeps_its_electrodes_and_all_it_is_not_given(mesh):
    conductivity = jnp.asarray(np.random.default_rng(5).uniform(0.5, 2.0, mesh.n_elements))
    shift = np.random.default_rng(6).uniform(-0.02, 0.02, (16, 2))
    model = de.ForwardModel(mesh, PROTOCOL, 0.02, electrode_shift=shift, electrode_margin=0.03, drive_current=2e-3)
    opposite = de.protocol.opposite(16)
    replaced = model.replace(protocol=opposite, contact_impedance=np.linspace(0.01, 0.03, 16))
    expected = de.ForwardModel(
        mesh, opposite, np.linspace(0.01, 0.03, 16), electrode_shift=shift, electrode_margin=0.03, drive_current=2e-3
    )
    np.testing.assert_array_equal(replaced.measure(conductivity), expected.measure(conductivity))
    assert replaced.system.electrode_margin == 0.03
    np.testing.assert_array_equal(model.replace().measure(conductivity), model.measure(conductivity))
    # A margin frees a model's electrodes, unmoved; a point model stays one.
    freed = de.ForwardModel(mesh, PROTOCOL, 0.02).replace(electrode_margin=0.01)
    assert np.all(np.asarray(freed.electrode_shift) == 0) and freed.system.electrode_margin == 0.01
    point = de.ForwardModel(mesh, PROTOCOL, electrode_model="point").replace(protocol=opposite)
    assert isinstance(point.system, de.assembly.PointElectrodeSystem) and point.electrode_shift is None
    with pytest.raises(ValueError, match="complete electrode model"):
        de.ForwardModel(mesh, PROTOCOL, electrode_model="point").replace(electrode_margin=0.01)
