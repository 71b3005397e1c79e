"""The forward model against the series solution of the complete electrode model on the disc.

`analytic.cem_disc_electrode_potentials` solves the CEM on the unit disc by a spectral Galerkin
method to about 1e-9 relative (tests/analytic.py), far below every discretisation error here.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from analytic import cem_disc_electrode_potentials

import diffeit as de

ANGLES = 2 * np.pi * np.arange(16) / 16  # electrode centres of de.mesh.disc
HALF_ANGLE = 0.1  # electrode width 0.2 on the unit disc
PROTOCOL = de.protocol.adjacent(16)


def _series_voltages(contact_impedance, **inclusion) -> np.ndarray:
    potentials = cem_disc_electrode_potentials(
        1e-3 * PROTOCOL.drive, ANGLES, HALF_ANGLE, contact_impedance, **inclusion
    )
    return np.sum(PROTOCOL.measure * potentials[PROTOCOL.drive_index], axis=1)


def _fem_error(h: float, contact_impedance: float, reference: np.ndarray, inclusion=None) -> float:
    circles = () if inclusion is None else (inclusion[0],)
    mesh = de.mesh.disc(16, electrode_width=2 * HALF_ANGLE, h=h, interior_circles=circles)
    sigma = np.ones(mesh.n_elements)
    if inclusion is not None:
        radius, value = inclusion
        inside = np.all(np.linalg.norm(mesh.nodes[mesh.triangles], axis=2) <= radius + 1e-12, axis=1)
        sigma[inside] = value
    voltages = np.asarray(de.ForwardModel(mesh, PROTOCOL, contact_impedance).measure(jnp.asarray(sigma)))
    return float(np.linalg.norm(voltages - reference) / np.linalg.norm(reference))


def _rates(errors: list[float]) -> np.ndarray:
    return np.log2(np.array(errors[:-1]) / np.array(errors[1:]))


@pytest.mark.slow
def test_homogeneous_disc_converges_to_the_series_solution():
    """Errors of the 208 voltages fall as h^p with p -> 2 (the voltages are linear functionals
    of a solution whose gradient is only mildly singular at the electrode edges when z > 0;
    the polygonal boundary also errs by O(h^2)). Measured (z = 0.1): 4.1e-2, 1.3e-2, 4.1e-3,
    1.1e-3 at h = 0.2, 0.1, 0.05, 0.025: rates 1.66, 1.68, 1.86."""
    reference = _series_voltages(0.1)
    errors = [_fem_error(h, 0.1, reference) for h in (0.2, 0.1, 0.05)]
    assert np.all(_rates(errors) > 1.5), errors
    assert errors[-1] < 5e-3


@pytest.mark.slow
def test_homogeneous_disc_converges_for_small_contact_impedance():
    """z = 0.01: the contact layer is thinner than the finest elements here, so the rate is
    pre-asymptotic. Measured: 3.6e-2, 1.1e-2, 4.9e-3, 2.1e-3 (rates 1.75, 1.14, 1.20)."""
    reference = _series_voltages(0.01)
    errors = [_fem_error(h, 0.01, reference) for h in (0.2, 0.1, 0.05, 0.025)]
    assert np.all(_rates(errors) > 1.0), errors
    assert errors[-1] < 3e-3
    fine = _fem_error(0.025, 0.1, _series_voltages(0.1))
    assert fine < 1.5e-3


@pytest.mark.parametrize("inclusion_conductivity", [5.0, pytest.param(0.2, marks=pytest.mark.slow)])
def test_concentric_inclusion_matches_its_series_solution(inclusion_conductivity):
    """Inclusion of radius 0.5 on a mesh aligned to it. Measured: the inclusion moves the
    voltages by 16% (5x) and 23% (0.2x); the model errs by 1.3e-2, 4.4e-3, 1.1e-3 at
    h = 0.1, 0.05, 0.025 (rates 1.6, 2.0) for both."""
    reference = _series_voltages(0.1, inclusion_radius=0.5, inclusion_conductivity=inclusion_conductivity)
    homogeneous = _series_voltages(0.1)
    effect = np.linalg.norm(reference - homogeneous) / np.linalg.norm(reference)
    errors = [_fem_error(h, 0.1, reference, inclusion=(0.5, inclusion_conductivity)) for h in (0.1, 0.05)]
    assert errors[1] < errors[0] / 2.5, errors
    assert errors[1] < 0.05 * effect  # the model resolves the inclusion, not just the background
