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
from ..mesh import Mesh, centroid_distances, element_adjacency


class PriorOperator(NamedTuple):
    """A prior bound to a mesh (and, for NOSER, to a Jacobian): four functions of X.

    Each function takes NumPy X of shape (E,) or (E, k), a relative change per element
    (dsigma / sigma), and returns the shape of X. Iterative solvers use the factor:
    J P J^T = (S^T J^T)^T (S^T J^T) and P J^T y = S (S^T J^T y) cost one sparse solve with
    many right-hand sides, where P J^T costs two. Sparse factorisations are made once per
    mesh, by `AbstractPrior.bind`.

    Attributes:
        covariance: X -> P X.
        precision: X -> P^-1 X.
        root: X -> S X, for a factor P = S S^T.
        root_transpose: X -> S^T X.
    """

    covariance: Callable[[np.ndarray], np.ndarray]
    precision: Callable[[np.ndarray], np.ndarray]
    root: Callable[[np.ndarray], np.ndarray]
    root_transpose: Callable[[np.ndarray], np.ndarray]


class AbstractPrior(eqx.Module):
    """A prior covariance P on the relative change dsigma / sigma, one value per element.

    P is (E, E), symmetric positive definite, and never formed: a prior binds to a mesh
    (`bind`, `operator`) and applies P through sparse factorisations. Its parameters are
    static fields: a prior holds no arrays until it is bound to a mesh. The priors and their
    precisions are in docs/science.md#priors; `prior_named` picks one by name.
    """

    @abc.abstractmethod
    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """The prior on `mesh`, its sparse factorisations made once.

        Iterative solvers bind once and build an operator per iterate.

        Arguments:
            mesh: The mesh whose elements the prior covers.

        Returns:
            A function from the (M, E) normalised Jacobian to the `PriorOperator` (only NOSER
            reads the Jacobian).
        """

    def operator(self, mesh: Mesh, jacobian: np.ndarray) -> PriorOperator:
        """P bound to `mesh` (and `jacobian`): `bind(mesh)(jacobian)`.

        Arguments:
            mesh: The mesh whose elements the prior covers.
            jacobian: (M, E) the normalised Jacobian (only NOSER reads it).

        Returns:
            The `PriorOperator`.

        Raises:
            ValueError: For NOSER, when an element has zero sensitivity.
        """
        return self.bind(mesh)(jacobian)

    def covariance_times_jacobian_transpose(self, mesh: Mesh, jacobian: np.ndarray) -> np.ndarray:
        """P J^T for the normalised Jacobian J.

        Arguments:
            mesh: The mesh whose elements the prior covers.
            jacobian: (M, E) the normalised Jacobian J.

        Returns:
            (E, M) P J^T.

        Raises:
            ValueError: For NOSER, when an element has zero sensitivity.
        """
        return self.operator(mesh, jacobian).covariance(np.ascontiguousarray(jacobian.T))


class Tikhonov(AbstractPrior):
    """P = I: every element's change independent, equally likely."""

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """The identity on `mesh`, whatever the Jacobian.

        Arguments:
            mesh: The mesh (unused: the identity needs nothing from it).

        Returns:
            A function from the (M, E) normalised Jacobian to the identity `PriorOperator`.
        """
        identity = PriorOperator(np.array, np.array, np.array, np.array)
        return lambda jacobian: identity


class Noser(AbstractPrior):
    """NOSER: P = diag(J^T J)^-exponent (Cheney et al. 1990), J the normalised Jacobian.

    Elements the data see weakly (the centre) may change more, which evens out the
    sensitivity. EIDORS uses exponent 0.5, pyEIT's "kotre" method the same form with its `p`
    (default 0.2).

    Attributes:
        exponent: The power of diag(J^T J) in the precision (static, default 0.5).
    """

    exponent: float = eqx.field(static=True, default=0.5)

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """NOSER on `mesh`: the operator is built from each Jacobian.

        Arguments:
            mesh: The mesh (unused: NOSER reads the Jacobian only).

        Returns:
            A function from the (M, E) normalised Jacobian to the `PriorOperator`; it raises
            `ValueError` when an element has zero sensitivity (a zero column of J).
        """
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
    """P = (L + ridge I)^-2, L the graph Laplacian of element adjacency: smoothness.

    Elements sharing an edge are neighbours, weight 1. Penalises differences between
    neighbours, as EIDORS's `prior_laplace` (whose L^T L is singular on constants; the ridge,
    relative to the mean degree of 3, makes it invertible and leaves a uniform change a large
    but finite variance).

    Attributes:
        ridge: The multiple of I added to L (static, default 1e-2, positive).

    Raises:
        ValueError: For a ridge that is not positive.
    """

    ridge: float = eqx.field(static=True, default=1e-2)

    def __check_init__(self) -> None:
        if not self.ridge > 0:
            raise ValueError(f"ridge must be positive; got {self.ridge}")

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """The prior on `mesh`: L + ridge I factorised once (SuperLU), S = S^T = (L + ridge I)^-1.

        Arguments:
            mesh: The mesh whose element adjacency defines L.

        Returns:
            A function from the (M, E) normalised Jacobian (unused) to the `PriorOperator`.
        """
        first, second, _ = element_adjacency(mesh)
        root = _graph_laplacian(first, second, np.ones(len(first)), mesh.n_elements)
        root = (root + self.ridge * scipy.sparse.eye(mesh.n_elements)).tocsc()
        solve = _block_solver(splu_spd(root))
        operator = PriorOperator(lambda x: solve(solve(x)), lambda x: root @ (root @ x), solve, solve)
        return lambda jacobian: operator  # S = S^T = (L + ridge I)^-1


class Matern(AbstractPrior):
    """A Gaussian field with Matern covariance (smoothness nu = 1) of `correlation_length`.

    Applied through its sparse precision (Lindgren, Rue and Lindstrom 2011, the SPDE
    (kappa^2 - Laplacian) x = white noise): P^-1 = K C^-1 K with K = kappa^2 C + G, C the
    diagonal of element areas (m^2), G the finite-volume Laplacian of the element graph (flux
    |shared edge| / |centroid distance|, the distance along the sheet: on a curved skin, across
    the shared edge with the two triangles unfolded, `diffeit.mesh.centroid_distances`),
    kappa = sqrt(8 nu) / correlation_length. At the correlation length the correlation has
    fallen to about 0.14.

    Attributes:
        correlation_length: Metres (static, default 0.2, positive).

    Raises:
        ValueError: For a correlation length that is not positive.
    """

    correlation_length: float = eqx.field(static=True, default=0.2)

    def __check_init__(self) -> None:
        if not self.correlation_length > 0:
            raise ValueError(f"correlation_length must be positive (metres); got {self.correlation_length}")

    def bind(self, mesh: Mesh) -> Callable[[np.ndarray], PriorOperator]:
        """The prior on `mesh`: K factorised once (SuperLU), S = K^-1 C^(1/2).

        Arguments:
            mesh: The mesh whose elements (areas, adjacency, centroids) define K and C.

        Returns:
            A function from the (M, E) normalised Jacobian (unused) to the `PriorOperator`.
        """
        kappa = np.sqrt(8.0) / self.correlation_length
        first, second, edge_lengths = element_adjacency(mesh)
        distance = centroid_distances(mesh)  # along the sheet, on a curved one too
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
    """The prior called `name`, with its default parameters.

    Arguments:
        name: "tikhonov" (`Tikhonov`), "noser" (`Noser`), "laplace" (`Laplace`) or "matern"
            (`Matern`).

    Returns:
        A new instance of the prior.

    Raises:
        ValueError: For any other name.
    """
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
