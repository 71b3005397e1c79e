"""Prior operators: P, its inverse and its factor agree, and P is symmetric positive definite."""

import numpy as np
import pytest

from diffeit.inverse.priors import Laplace, Matern, Noser, Tikhonov, prior_named
from diffeit.mesh import element_adjacency


@pytest.mark.parametrize("prior", [Tikhonov(), Noser(), Noser(0.2), Laplace(), Matern(0.3)], ids=repr)
def test_covariance_precision_and_factor_agree(small_disc, prior):
    rng = np.random.default_rng(0)
    jacobian = rng.standard_normal((20, small_disc.n_elements))
    operator = prior.operator(small_disc, jacobian)
    x, y = rng.standard_normal((2, small_disc.n_elements))
    covariance_x = operator.covariance(x)
    np.testing.assert_allclose(operator.precision(covariance_x), x, atol=1e-10 * np.abs(x).max())
    np.testing.assert_allclose(operator.root(operator.root_transpose(x)), covariance_x, rtol=1e-10, atol=1e-14)
    assert y @ covariance_x == pytest.approx(x @ operator.covariance(y), rel=1e-10)  # symmetric
    assert x @ covariance_x > 0
    columns = operator.covariance(np.stack([x, y], axis=1))  # (E, k) at once
    np.testing.assert_allclose(columns[:, 1], operator.covariance(y), rtol=1e-12, atol=1e-15)


def test_matern_correlation_falls_with_distance(small_disc):
    """The Matern prior's correlation between element pairs falls off with their distance, and
    faster for a shorter correlation length."""
    centroids = small_disc.element_centroids
    source = np.argmin(np.linalg.norm(centroids, axis=1))  # an element at the centre
    distance = np.linalg.norm(centroids - centroids[source], axis=1)
    near, far = (distance > 0.2) & (distance < 0.3), distance > 0.6
    for length in (0.2, 0.5):
        column = Matern(length).operator(small_disc, np.zeros((1, 1))).covariance(np.eye(small_disc.n_elements)[source])
        correlation = column / column[source]
        assert correlation[near].mean() > correlation[far].mean()
    short = Matern(0.2).operator(small_disc, np.zeros((1, 1))).covariance(np.eye(small_disc.n_elements)[source])
    long = Matern(0.5).operator(small_disc, np.zeros((1, 1))).covariance(np.eye(small_disc.n_elements)[source])
    assert (short / short[source])[far].mean() < (long / long[source])[far].mean()


def test_element_adjacency_counts_interior_edges(small_disc):
    first, second, lengths = element_adjacency(small_disc)
    boundary = len(small_disc.boundary_edges)
    assert len(first) == (3 * small_disc.n_elements - boundary) // 2
    assert np.all(first != second) and np.all(lengths > 0)


def test_bad_priors_are_refused(small_disc):
    with pytest.raises(ValueError, match="unknown prior 'smooth'"):
        prior_named("smooth")
    with pytest.raises(ValueError, match="ridge must be positive"):
        Laplace(0.0).operator(small_disc, np.zeros((1, small_disc.n_elements)))
    with pytest.raises(ValueError, match="zero sensitivity"):
        Noser().operator(small_disc, np.zeros((1, small_disc.n_elements)))
