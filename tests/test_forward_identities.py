"""Identities the complete electrode model satisfies exactly, so its discretisation must too: on
a disc, a rectangle and an L-shaped polygon (the `sheet` fixtures)."""

import jax
import jax.numpy as jnp
import numpy as np
import skfem
from skfem.helpers import dot, grad

import diffeit as de

Z_PER_ELECTRODE = np.linspace(0.005, 0.05, 16)


def test_reciprocity_of_adjacent_measurements(sheet_model, sheet_conductivity):
    voltages = np.asarray(sheet_model.measure(sheet_conductivity, Z_PER_ELECTRODE))
    protocol = sheet_model.protocol
    pair = {}  # (drive k, measured pair m) -> voltage
    for value, k, weights in zip(voltages, protocol.drive_index, protocol.measure, strict=True):
        pair[k, int(np.flatnonzero(weights == 1)[0])] = value
    # Drive pattern of pair m is minus its measurement pattern, so V(k, m) = V(m, k).
    differences = [abs(v - pair[m, k]) for (k, m), v in pair.items()]
    assert len(differences) == 208
    assert max(differences) < 1e-10 * np.abs(voltages).max()


def test_scaling_conductivity_and_contact_impedance(sheet_model, sheet_conductivity):
    c = 7.3
    base = sheet_model.measure(sheet_conductivity, Z_PER_ELECTRODE)
    scaled = sheet_model.measure(c * sheet_conductivity, Z_PER_ELECTRODE / c)
    np.testing.assert_allclose(scaled, base / c, rtol=1e-11)


def test_voltages_are_linear_in_the_drive_current(sheet, sheet_model, sheet_conductivity):
    doubled = de.ForwardModel(sheet, sheet_model.protocol, 0.01, drive_current=2e-3)
    np.testing.assert_allclose(
        doubled.measure(sheet_conductivity), 2 * sheet_model.measure(sheet_conductivity), rtol=1e-12
    )
    np.testing.assert_allclose(
        sheet_model.jacobian(sheet_conductivity) * 2, doubled.jacobian(sheet_conductivity), rtol=1e-12
    )


def test_power_identity_against_an_independent_assembly(sheet, sheet_model, sheet_conductivity):
    """sum_l I_l U_l = int sigma |grad u|^2 + sum_l int_(e_l) (U_l - u)^2 / z_l per drive, with the
    sheet energy assembled by scikit-fem."""
    potentials = sheet_model.potentials(sheet_conductivity, Z_PER_ELECTRODE)
    skmesh = skfem.MeshTri(sheet.nodes.T, sheet.triangles.T)
    basis = skfem.Basis(skmesh, skfem.ElementTriP1())
    sigma = basis.with_element(skfem.ElementTriP0()).interpolate(np.asarray(sheet_conductivity))

    @skfem.BilinearForm
    def energy_form(u, v, w):
        return w.sigma * dot(grad(u), grad(v))

    stiffness = energy_form.assemble(basis, sigma=sigma)
    currents = sheet_model.drive_current * sheet_model.protocol.drive
    for nodal, electrode, current in zip(
        np.asarray(potentials.nodal), np.asarray(potentials.electrode), currents, strict=True
    ):
        sheet_energy = nodal @ stiffness @ nodal
        contact = 0.0
        for chain, level, z in zip(sheet.electrodes, electrode, Z_PER_ELECTRODE, strict=True):
            a, b = level - nodal[chain[:-1]], level - nodal[chain[1:]]
            length = np.linalg.norm(np.diff(sheet.nodes[chain], axis=0), axis=1)
            contact += np.sum(length * (a * a + a * b + b * b) / 3) / z  # exact for linear u
        np.testing.assert_allclose(current @ electrode, sheet_energy + contact, rtol=1e-11)
    assert np.all(np.asarray(potentials.relative_residual) < 1e-12)


def test_electrode_potentials_sum_to_zero_and_currents_balance(sheet_model, sheet_conductivity):
    potentials = sheet_model.potentials(sheet_conductivity)
    np.testing.assert_allclose(potentials.electrode.sum(axis=1), 0.0, atol=1e-15)
    assert potentials.nodal.shape == (16, sheet_model.mesh.n_nodes)
    # Current through electrode l is int (U_l - u)/z_l: it must equal the driven current.
    z = 0.01
    for nodal, electrode, current in zip(
        np.asarray(potentials.nodal),
        np.asarray(potentials.electrode),
        sheet_model.drive_current * sheet_model.protocol.drive,
        strict=True,
    ):
        through = []
        for chain, level in zip(sheet_model.mesh.electrodes, electrode, strict=True):
            length = np.linalg.norm(np.diff(sheet_model.mesh.nodes[chain], axis=0), axis=1)
            mean_gap = level - 0.5 * (nodal[chain[:-1]] + nodal[chain[1:]])
            through.append(np.sum(length * mean_gap) / z)
        np.testing.assert_allclose(through, current, atol=1e-12 * sheet_model.drive_current)


def test_jacobian_matches_central_differences(sheet_model, sheet_conductivity):
    jacobian = sheet_model.jacobian(sheet_conductivity, Z_PER_ELECTRODE)
    direction = np.random.default_rng(8).normal(size=sheet_model.n_elements) * sheet_conductivity
    step = 1e-4
    difference = (
        sheet_model.measure(sheet_conductivity + step * direction, Z_PER_ELECTRODE)
        - sheet_model.measure(sheet_conductivity - step * direction, Z_PER_ELECTRODE)
    ) / (2 * step)
    expected = np.asarray(jacobian @ direction)
    assert np.abs(difference - expected).max() < 1e-6 * np.abs(expected).max()


def test_measure_works_under_jit_vmap_and_as_a_pytree(small_model, rough_conductivity):
    expected = small_model.measure(rough_conductivity)
    np.testing.assert_allclose(jax.jit(small_model.measure)(rough_conductivity), expected, rtol=1e-13)
    batch = jnp.stack([rough_conductivity, 2 * rough_conductivity, 0.5 * rough_conductivity])
    batched = jax.vmap(small_model.measure)(batch)
    one_by_one = np.stack([small_model.measure(sigma) for sigma in batch])
    np.testing.assert_allclose(batched, one_by_one, rtol=1e-12)
    assert not np.allclose(one_by_one[1], one_by_one[0] / 2)  # the contact impedance did not scale
    through_jit = jax.jit(lambda model, sigma: model.measure(sigma))(small_model, rough_conductivity)
    np.testing.assert_allclose(through_jit, expected, rtol=1e-13)
    leaves = jax.tree_util.tree_leaves(small_model)
    assert len(leaves) == 1 and leaves[0].shape == (16,)  # the contact impedance
