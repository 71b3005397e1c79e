"""Priors for linearised reconstruction, applied through their covariance P = (R^T R)^-1.

A prior here is the covariance of the relative conductivity change x = dsigma / background,
one value per element. The solvers only ever need P J^T for the (normalised) Jacobian J: the
measurement-space formulation solves an n_meas x n_meas system, so no dense E x E matrix is
formed; the smoothness priors apply P by sparse factorisations (SciPy, once per set-up).

| prior | R^T R (the precision P^-1) | reads |
|---|---|---|
| `Tikhonov()` | I | small changes |
| `Noser(exponent)` | diag(J^T J)^exponent | EIDORS's NOSER (0.5), pyEIT's "kotre" (its p) |
| `Laplace(ridge)` | (L + ridge I)^2, L the element adjacency graph Laplacian | EIDORS's `prior_laplace` |
| `Matern(correlation_length)` | K C^-1 K, K = kappa^2 C + G | a Gaussian field of that correlation length |

The scale of P is immaterial: `diffeit.inverse.OneStep` normalises it (see there).
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from ..linear_solve import splu_spd
from ..mesh import Mesh, element_adjacency


class PriorOperator(NamedTuple):
    """A prior bound to a mesh (and, for NOSER, to a Jacobian), for X of shape (E,) or (E, k):

    - `covariance(X)` = P X and `precision(X)` = P^-1 X;
    - `root(X)` = S X and `root_transpose(X)` = S^T X for a factor P = S S^T.

    Iterative solvers use the factor: J P J^T = (S^T J^T)^T (S^T J^T) and P J^T y = S (S^T J^T y)
    cost one sparse solve with many right-hand sides, where P J^T costs two. Sparse
    factorisations are made once per mesh, by `AbstractPrior.bind`.
    """

    covariance: Callable[[np.ndarray], np.ndarray]
    precision: Callable[[np.ndarray], np.ndarray]
    root: Callable[[np.ndarray], np.ndarray]
    root_transpose: Callable[[np.ndarray], np.ndarray]


class AbstractPrior(eqx.Module):
    """A prior covariance P (E x E, symmetric positive definite) on the relative change. Its
    parameters are static fields: a prior holds no arrays until it is bound to a mesh."""

    @abc.abstractmethod
    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """The prior on `mesh`, its sparse factorisations made once: a function from the
        normalised Jacobian (M, E) to the operator (only NOSER reads the Jacobian). Iterative
        solvers bind once and build an operator per iterate."""

    def operator(self, mesh: Mesh, jacobian: np.ndarray) -> PriorOperator:
        """P bound to `mesh`; `jacobian` (M, E) is the normalised Jacobian (only NOSER reads it)."""
        return self.bind(mesh)(jacobian)

    def covariance_times_jacobian_transpose(self, mesh: Mesh, jacobian: np.ndarray) -> np.ndarray:
        """(E, M) P J^T for the (M, E) normalised Jacobian `jacobian`."""
        return self.operator(mesh, jacobian).covariance(np.ascontiguousarray(jacobian.T))


class Tikhonov(AbstractPrior):
    """P = I: every element's change independent, equally likely."""

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        identity = PriorOperator(np.array, np.array, np.array, np.array)
        return lambda jacobian: identity


class Noser(AbstractPrior):
    """P = diag(J^T J)^-exponent (Cheney et al. 1990): elements the data see weakly (the
    centre) may change more, which evens out the sensitivity. EIDORS uses exponent 0.5,
    pyEIT's "kotre" method the same form with its `p` (default 0.2)."""

    exponent: float = eqx.field(static=True, default=0.5)

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        return self._operator

    def _operator(self, jacobian: np.ndarray) -> PriorOperator:
        sensitivity = np.sum(jacobian**2, axis=0)
        if np.any(sensitivity <= 0):
            raise ValueError(f"{np.count_nonzero(sensitivity <= 0)} element(s) have zero sensitivity: NOSER undefined")
        weights = sensitivity**self.exponent

        def shaped(x: np.ndarray) -> np.ndarray:
            return weights.reshape((-1,) + (1,) * (np.ndim(x) - 1))

        return PriorOperator(
            lambda x: x / shaped(x),
            lambda x: x * shaped(x),
            lambda x: x / np.sqrt(shaped(x)),
            lambda x: x / np.sqrt(shaped(x)),
        )


class Laplace(AbstractPrior):
    """P = (L + ridge I)^-2 with L the graph Laplacian of element adjacency (elements sharing
    an edge are neighbours, weight 1): penalises differences between neighbours, as EIDORS's
    `prior_laplace` (whose L^T L is singular on constants; the ridge, relative to the mean
    degree of 3, makes it invertible and leaves a uniform change a large but finite variance)."""

    ridge: float = eqx.field(static=True, default=1e-2)

    def __check_init__(self) -> None:
        if not self.ridge > 0:
            raise ValueError(f"ridge must be positive; got {self.ridge}")

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        first, second, _ = element_adjacency(mesh)
        root = _graph_laplacian(first, second, np.ones(len(first)), mesh.n_elements)
        root = (root + self.ridge * scipy.sparse.eye(mesh.n_elements)).tocsc()
        solve = _block_solver(splu_spd(root))
        operator = PriorOperator(lambda x: solve(solve(x)), lambda x: root @ (root @ x), solve, solve)
        return lambda jacobian: operator  # S = S^T = (L + ridge I)^-1


class Matern(AbstractPrior):
    """A Gaussian field with Matern covariance (smoothness nu = 1) of `correlation_length`
    (metres), through its sparse precision (Lindgren, Rue and Lindstrom 2011, the SPDE
    (kappa^2 - Laplacian) x = white noise): P^-1 = K C^-1 K with K = kappa^2 C + G, C the
    diagonal of element areas, G the finite-volume Laplacian of the element graph (flux
    |shared edge| / |centroid distance|), kappa = sqrt(8 nu) / correlation_length. At the
    correlation length the correlation has fallen to about 0.14."""

    correlation_length: float = eqx.field(static=True, default=0.2)

    def __check_init__(self) -> None:
        if not self.correlation_length > 0:
            raise ValueError(f"correlation_length must be positive (metres); got {self.correlation_length}")

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        kappa = np.sqrt(8.0) / self.correlation_length
        first, second, edge_lengths = element_adjacency(mesh)
        distance = np.linalg.norm(mesh.element_centroids[first] - mesh.element_centroids[second], axis=1)
        laplacian = _graph_laplacian(first, second, edge_lengths / distance, mesh.n_elements)
        areas = mesh.element_areas
        operator = (kappa**2 * scipy.sparse.diags(areas) + laplacian).tocsc()
        solve = _block_solver(splu_spd(operator))

        def per_element(x: np.ndarray) -> np.ndarray:
            return areas.reshape((-1,) + (1,) * (np.ndim(x) - 1))

        # S = K^-1 C^(1/2): S S^T = K^-1 C K^-1 (K is symmetric).
        bound = PriorOperator(
            lambda x: solve(per_element(x) * solve(x)),
            lambda x: operator @ ((operator @ x) / per_element(x)),
            lambda x: solve(np.sqrt(per_element(x)) * x),
            lambda x: np.sqrt(per_element(x)) * solve(x),
        )
        return lambda jacobian: bound


def prior_named(name: str) -> AbstractPrior:
    """The prior called `name` with its default parameters: "tikhonov", "noser", "laplace",
    "matern"."""
    priors = {"tikhonov": Tikhonov, "noser": Noser, "laplace": Laplace, "matern": Matern}
    if name not in priors:
        raise ValueError(f"unknown prior {name!r}; choose one of {sorted(priors)} or pass a prior instance")
    return priors[name]()


def _block_solver(factor: scipy.sparse.linalg.SuperLU) -> Callable[[np.ndarray], np.ndarray]:
    """`factor.solve` for a vector or a block of columns (E, k), the block in column-major
    order: SuperLU solves column by column, and a row-major block costs it a strided copy."""
    return lambda x: factor.solve(np.asfortranarray(x))


def _graph_laplacian(first: np.ndarray, second: np.ndarray, weights: np.ndarray, n: int) -> scipy.sparse.csr_matrix:
    adjacency = scipy.sparse.coo_matrix((weights, (first, second)), shape=(n, n))
    adjacency = (adjacency + adjacency.T).tocsr()
    return scipy.sparse.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
