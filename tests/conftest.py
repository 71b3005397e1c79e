import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de


@pytest.fixture(scope="session")
def small_disc() -> de.Mesh:
    return de.mesh.disc(16, electrode_width=0.2, h=0.15)


@pytest.fixture(scope="session")
def small_model(small_disc) -> de.ForwardModel:
    return de.ForwardModel(small_disc, de.protocol.adjacent(16), contact_impedance=0.01)


@pytest.fixture
def rough_conductivity(small_disc):
    """A seeded, strongly non-uniform conductivity (S/sq) around 1."""
    rng = np.random.default_rng(1234)
    return jnp.asarray(np.exp(rng.normal(0.0, 0.5, small_disc.n_elements)))
