"""The one differentiable linear solve of diffeit, and its backends.

Every forward and adjoint solve goes through `solve_spd`: a symmetric positive definite system
given by its values on a fixed `SparsityPattern`. Differentiation is defined once, here, by
`jax.lax.custom_linear_solve` (implicit differentiation: a tangent or cotangent costs one more
solve with the same matrix), so backends only have to solve.
"""

from __future__ import annotations

import abc
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from ._arrays import StaticData, fingerprint, is_concrete
from ._threads import host_algebra, one_blas_thread_in_xla
from .results import RESULTS


@dataclass(eq=False)
class SparsityPattern(StaticData):
    """The nonzero positions of a symmetric n x n matrix, in compressed sparse column order.

    Static data for JAX, compared and hashed by content: values live in a separate (nnz,)
    array, traced and differentiable. Build one with `from_entries`.

    Attributes:
        rows: (nnz,) the row of each stored entry, sorted by column, then row.
        cols: (nnz,) the column of each stored entry.
        indptr: (size + 1,) where each column's entries start in `rows` (CSC).
        size: n, the number of rows and columns.
        fingerprint: A digest of the pattern, the key of its cached orderings.
    """

    rows: np.ndarray
    cols: np.ndarray
    indptr: np.ndarray
    size: int
    fingerprint: bytes = field(repr=False)

    @classmethod
    def from_entries(cls, rows: np.ndarray, cols: np.ndarray, size: int) -> tuple[SparsityPattern, np.ndarray]:
        """The pattern holding the given (row, col) entries, and the slot of each entry in it.

        Repeated entries share a slot: assembling `values = zeros(nnz).at[slots].add(entries)`
        sums them, as finite-element assembly does.

        Arguments:
            rows: The row of each entry, integers in [0, size), any shape.
            cols: The column of each entry, the shape of `rows`.
            size: n, the number of rows and columns.

        Returns:
            (the `SparsityPattern`, the (number of entries,) slot of each entry in it).

        Raises:
            ValueError: When the entries do not form a symmetric pattern.
        """
        flat = np.asarray(cols, dtype=np.int64) * size + np.asarray(rows, dtype=np.int64)
        unique, slots = np.unique(flat, return_inverse=True)  # sorted by column, then row
        pattern_cols, pattern_rows = np.divmod(unique, size)
        indptr = np.searchsorted(pattern_cols, np.arange(size + 1)).astype(np.int64)
        if not np.array_equal(np.sort(pattern_rows * size + pattern_cols), unique):
            raise ValueError("the sparsity pattern is not symmetric")
        pattern = cls(pattern_rows, pattern_cols, indptr, size, fingerprint(np.int64(size), unique))
        return pattern, slots.ravel()

    @property
    def nnz(self) -> int:
        """The number of stored entries."""
        return len(self.rows)

    @property
    def diagonal_slots(self) -> np.ndarray:
        """(size,) the slot of each diagonal entry (every row of an SPD pattern has one).

        Raises:
            ValueError: When a diagonal entry is missing.
        """
        slots = np.flatnonzero(self.rows == self.cols)
        if len(slots) != self.size:
            raise ValueError("the sparsity pattern lacks diagonal entries")
        return slots[np.argsort(self.cols[slots])]

    def matvec(self, values: jax.Array, x: jax.Array) -> jax.Array:
        """The product A @ x of the matrix with `values` on the pattern and `x`.

        A is symmetric, so A @ x = A^T @ x, which sums over the column-sorted indices. A JAX
        function, differentiable in `values` and `x`.

        Arguments:
            values: (nnz,) the matrix entries, in the pattern's order.
            x: (n,) or (n, k).

        Returns:
            A @ x, the shape of `x`.
        """
        products = values.reshape((-1,) + (1,) * (x.ndim - 1)) * x[self.rows]
        return jax.ops.segment_sum(products, self.cols, num_segments=self.size, indices_are_sorted=True)

    def to_scipy(self, values: np.ndarray) -> scipy.sparse.csc_matrix:
        """The matrix with `values` on the pattern, as a SciPy CSC matrix.

        Arguments:
            values: (nnz,) the matrix entries, in the pattern's order (NumPy).

        Returns:
            The (size, size) `scipy.sparse.csc_matrix`.
        """
        return scipy.sparse.csc_matrix((values, self.rows, self.indptr), shape=(self.size, self.size))


class AbstractLinearSolver(eqx.Module):
    """A backend: solves A X = B for a symmetric positive definite A given on a pattern.

    A backend splits its work in two: `factorise` does what depends on the matrix alone, once
    per matrix, and `solve_factorised` solves with it. `solve_spd` factorises once and hands
    the factor to every solve with that matrix (the forward solve, the adjoint solve of a
    gradient, the solves of a Jacobian). Neither need be differentiable (`solve_spd` defines
    derivatives); both must work under `jax.vmap`. `values` are (nnz,), `rhs` (n, k).

    A backend is an `equinox.Module` of static settings (no array leaves): models hold it in a
    static field, so equal backends key the same compiled functions. The backends are
    `HostSparse`, `DenseCholesky` and `ConjugateGradient`; `solver_named` picks one by name.
    """

    @abc.abstractmethod
    def factorise(self, pattern: SparsityPattern, values: jax.Array) -> Any:
        """The factor of the matrix with `values` on `pattern`: a pytree of arrays.

        Arguments:
            pattern: The sparsity pattern.
            values: (nnz,) the matrix entries.

        Returns:
            What `solve_factorised` needs to solve with this matrix.
        """

    @abc.abstractmethod
    def solve_factorised(self, pattern: SparsityPattern, factor: Any, rhs: jax.Array) -> tuple[jax.Array, RESULTS]:
        """Solve with a factor made by `factorise`.

        Arguments:
            pattern: The sparsity pattern `factor` was made on.
            factor: The output of `factorise`.
            rhs: (n, k) the right-hand sides B.

        Returns:
            (X = A^-1 B, (n, k), for the matrix `factor` was made from; the `RESULTS` code of
            the solve).
        """

    def solve(self, pattern: SparsityPattern, values: jax.Array, rhs: jax.Array) -> jax.Array:
        """X = A^-1 B: factorise, then solve (not differentiable: see `solve_spd`).

        Arguments:
            pattern: The sparsity pattern.
            values: (nnz,) the matrix entries.
            rhs: (n, k) the right-hand sides B.

        Returns:
            (n, k) X.
        """
        return self.solve_factorised(pattern, self.factorise(pattern, values), rhs)[0]


class _FactorCache:
    """The host factorisations of one `HostSparse`: the fill-reducing order of each pattern
    (it depends on the structure only) and the last factorisations, keyed by the pattern and
    a digest of the values. Thread-safe: XLA may run callbacks concurrently."""

    ORDERINGS_KEPT = 8

    def __init__(self) -> None:
        self.orderings: OrderedDict[bytes, _Ordering] = OrderedDict()
        self.factors: OrderedDict[tuple[bytes, bytes], _Factor | None] = OrderedDict()
        self.lock = threading.Lock()

    def clear(self) -> None:
        with self.lock:
            self.orderings.clear()
            self.factors.clear()

    # A pickled solver (a model sent to another process) arrives with an empty cache.
    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.__init__()


class HostSparse(AbstractLinearSolver):
    """Sparse LU (SciPy's SuperLU, symmetric mode) on the host, through `jax.pure_callback`.

    The CPU default. Under `vmap` all right-hand sides of one matrix go to the host in one call
    and share one factorisation. The solver keeps the last `cache_size` factorisations, keyed
    by the matrix values, so a forward solve and its adjoint (separate host calls) factorise
    once; `clear_cache()` empties it. Equal instances (the same `cache_size`) are
    interchangeable: a function compiled with one serves models holding the other, with the
    first one's cache. Computes in float64 whatever the input dtype. A matrix that cannot be
    factorised gives NaN and `RESULTS.nonfinite`, not an exception (exceptions cannot cross the
    callback).

    Arguments:
        cache_size: How many factorisations to keep (at least one is kept).

    Attributes:
        cache_size: How many factorisations the solver keeps (static).
    """

    cache_size: int = eqx.field(static=True)
    _cache: _FactorCache = eqx.field(static=True, repr=False)

    def __init__(self, cache_size: int = 4) -> None:
        self.cache_size = int(cache_size)
        self._cache = _FactorCache()

    # Equal settings are interchangeable, whatever each instance has cached.
    def __eq__(self, other: object) -> bool:
        return type(other) is HostSparse and other.cache_size == self.cache_size

    def __hash__(self) -> int:
        return hash((HostSparse, self.cache_size))

    def factorise(self, pattern: SparsityPattern, values: jax.Array) -> jax.Array:
        """The values themselves: the host factorises them in the first solve, and caches it.

        Arguments:
            pattern: The sparsity pattern.
            values: (nnz,) the matrix entries.

        Returns:
            `values`.
        """
        # The factorisation happens on the host, in the first solve's callback; later solves
        # with the same values find it in the cache.
        return values

    def solve_factorised(
        self, pattern: SparsityPattern, factor: jax.Array, rhs: jax.Array
    ) -> tuple[jax.Array, RESULTS]:
        """Solve on the host with SciPy's SuperLU, reusing a cached factorisation.

        Arguments:
            pattern: The sparsity pattern.
            factor: (nnz,) the matrix entries (from `factorise`).
            rhs: (n, k) the right-hand sides B.

        Returns:
            (X = A^-1 B, (n, k), in the dtype of `rhs`; `RESULTS.nonfinite` for a matrix that
            could not be factorised, else `RESULTS.successful`).
        """

        def host(values: np.ndarray, rhs: np.ndarray) -> np.ndarray:
            return _host_solve(pattern, np.asarray(values), np.asarray(rhs), self.cache_size, self._cache)

        # expand_dims: an unbatched argument arrives with a leading axis of size 1, so a batch
        # of right-hand sides meets one matrix in a single call.
        x = jax.pure_callback(host, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), factor, rhs, vmap_method="expand_dims")
        return x, _finite_result(x)

    def clear_cache(self) -> None:
        """Forget every factorisation and ordering this solver holds."""
        self._cache.clear()


@dataclass(frozen=True)
class _Ordering:
    """A pattern symmetrically permuted by a fill-reducing order, in CSC form: the permuted
    matrix is A[order][:, order], its data `values[take]`."""

    order: np.ndarray
    take: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray


@dataclass(frozen=True)
class _Factor:
    """The sparse LU factors of a permuted matrix; `solve` undoes the permutation."""

    lu: scipy.sparse.linalg.SuperLU
    order: np.ndarray

    def solve(self, columns: np.ndarray) -> np.ndarray:
        solution = np.empty_like(columns, dtype=np.float64)
        solution[self.order] = self.lu.solve(np.asarray(columns[self.order], dtype=np.float64))
        return solution


def splu_spd(matrix: scipy.sparse.csc_matrix, permc_spec: str = "MMD_AT_PLUS_A") -> scipy.sparse.linalg.SuperLU:
    """Sparse LU of a symmetric positive definite matrix (SciPy's SuperLU).

    Diagonal pivots and symmetric mode (right for SPD, and they keep the order), by default
    with a symmetric fill-reducing order (less fill than SuperLU's default on finite-element
    and graph matrices).

    Arguments:
        matrix: The (n, n) symmetric positive definite matrix, CSC.
        permc_spec: SuperLU's column ordering: "MMD_AT_PLUS_A" (the default, symmetric),
            "NATURAL" (none: the matrix is already ordered), or another of SuperLU's.

    Returns:
        The `scipy.sparse.linalg.SuperLU` factorisation.

    Raises:
        RuntimeError: For an exactly singular matrix (SuperLU's).
    """
    # MMD_AT_PLUS_A gave about 40% less fill than SuperLU's default (COLAMD) on
    # finite-element and graph matrices.
    return scipy.sparse.linalg.splu(
        matrix, permc_spec=permc_spec, diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )


def _ordering(pattern: SparsityPattern, cache: _FactorCache) -> _Ordering:
    """The fill-reducing order of a pattern, computed once (it depends on the structure only):
    later factorisations skip SuperLU's ordering step, about a quarter of their time."""
    with cache.lock:
        if pattern.fingerprint in cache.orderings:
            return cache.orderings[pattern.fingerprint]
    # Any SPD matrix on the pattern gives the order: a graph Laplacian plus the identity.
    off_diagonal = pattern.rows != pattern.cols
    degree = np.bincount(pattern.cols[off_diagonal], minlength=pattern.size)
    laplacian = np.where(off_diagonal, -1.0, degree[pattern.rows] + 1.0)
    position = splu_spd(pattern.to_scipy(laplacian)).perm_c
    rows, cols = position[pattern.rows], position[pattern.cols]
    take = np.argsort(cols * pattern.size + rows)
    indptr = np.searchsorted(cols[take], np.arange(pattern.size + 1)).astype(np.int64)
    ordering = _Ordering(np.argsort(position), take, rows[take], indptr)
    with cache.lock:
        cache.orderings[pattern.fingerprint] = ordering
        while len(cache.orderings) > cache.ORDERINGS_KEPT:
            cache.orderings.popitem(last=False)
    return ordering


def _factorise(pattern: SparsityPattern, values: np.ndarray, cache_size: int, cache: _FactorCache) -> _Factor | None:
    values = np.ascontiguousarray(values, dtype=np.float64)
    key = (pattern.fingerprint, fingerprint(values))
    with cache.lock:
        if key in cache.factors:
            cache.factors.move_to_end(key)
            return cache.factors[key]
    ordering = _ordering(pattern, cache)
    permuted = scipy.sparse.csc_matrix(
        (values[ordering.take], ordering.indices, ordering.indptr), shape=(pattern.size, pattern.size)
    )
    try:
        factor = _Factor(splu_spd(permuted, "NATURAL"), ordering.order)
    except RuntimeError:  # exactly singular
        factor = None
    with cache.lock:
        cache.factors[key] = factor
        while len(cache.factors) > max(cache_size, 1):
            cache.factors.popitem(last=False)
    return factor


@host_algebra
def _host_solve(
    pattern: SparsityPattern, values: np.ndarray, rhs: np.ndarray, cache_size: int, cache: _FactorCache
) -> np.ndarray:
    batch = np.broadcast_shapes(values.shape[:-1], rhs.shape[:-2])
    n, k = rhs.shape[-2:]
    matrices = np.broadcast_to(values, batch + values.shape[-1:]) if values[..., 0].size > 1 else values
    matrices = matrices.reshape(-1, pattern.nnz)
    if len(matrices) == 1:
        # One matrix: every right-hand side of the batch in one triangular solve.
        columns = np.moveaxis(np.broadcast_to(rhs, (*batch, n, k)).reshape(-1, n, k), 1, 0).reshape(n, -1)
        solution = _solve_columns(_factorise(pattern, matrices[0], cache_size, cache), columns)
        solution = np.moveaxis(solution.reshape(n, -1, k), 0, 1)
    else:
        right = np.broadcast_to(rhs, (*batch, n, k)).reshape(-1, n, k)
        solution = np.stack(
            [_solve_columns(_factorise(pattern, m, cache_size, cache), b) for m, b in zip(matrices, right, strict=True)]
        )
    return solution.reshape((*batch, n, k)).astype(rhs.dtype, copy=False)


def _solve_columns(factor: _Factor | None, columns: np.ndarray) -> np.ndarray:
    if factor is None:
        return np.full(columns.shape, np.nan)
    return factor.solve(columns)


class DenseCholesky(AbstractLinearSolver):
    """Dense Cholesky factorisation in JAX (XLA), in the dtype of the values.

    For small meshes and for accelerators: the n x n matrix is formed, so memory grows as n^2
    and time as n^3 (a few thousand unknowns at most). Runs under jit and vmap; on CPU, XLA's
    Cholesky and triangular solves call OpenBLAS, which runs on one thread while they do (see
    `diffeit._threads`), and a vmapped batch is factorised and solved one matrix at a time
    (`_one_at_a_time_on_cpu`). A matrix that is not positive definite (in the working
    precision) gives NaN and `RESULTS.nonfinite`.
    `refinement_steps` steps of iterative refinement follow the triangular solves.

    Attributes:
        refinement_steps: Steps of iterative refinement after each solve (static, default 1).
    """

    refinement_steps: int = eqx.field(static=True, default=1)

    def factorise(self, pattern: SparsityPattern, values: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The dense Cholesky factor of the matrix, and its values for iterative refinement.

        Arguments:
            pattern: The sparsity pattern.
            values: (nnz,) the matrix entries.

        Returns:
            (the (n, n) lower Cholesky factor, NaN where the matrix is not positive definite;
            the (nnz,) values, for the refinement's residual).
        """
        matrix = jnp.zeros((pattern.size, pattern.size), values.dtype).at[pattern.rows, pattern.cols].set(values)
        return one_blas_thread_in_xla(_cholesky)(matrix), values

    def solve_factorised(
        self, pattern: SparsityPattern, factor: tuple[jax.Array, jax.Array], rhs: jax.Array
    ) -> tuple[jax.Array, RESULTS]:
        """Triangular solves with the Cholesky factor, then `refinement_steps` of refinement.

        Arguments:
            pattern: The sparsity pattern.
            factor: The output of `factorise`.
            rhs: (n, k) the right-hand sides B.

        Returns:
            (X = A^-1 B, (n, k), in the dtype of `rhs`; `RESULTS.nonfinite` where X is not
            finite, else `RESULTS.successful`).
        """
        lower, values = factor

        @_one_at_a_time_on_cpu
        def refined(lower: jax.Array, values: jax.Array, b: jax.Array) -> jax.Array:
            x = jax.scipy.linalg.cho_solve((lower, True), b)
            # Cholesky without pivoting is normwise but not componentwise backward stable: with
            # entries spanning many decades (contact impedance 1e-9, contrast 1e6) a step of
            # iterative refinement, O(n^2) against the O(n^3) factorisation, restores it.
            for _ in range(self.refinement_steps):
                x = x + jax.scipy.linalg.cho_solve((lower, True), b - pattern.matvec(values, x))
            return x

        x = one_blas_thread_in_xla(lambda b: refined(lower, values, b))(rhs.astype(values.dtype)).astype(rhs.dtype)
        return x, _finite_result(x)


def _one_at_a_time_on_cpu(function: Callable[..., jax.Array]) -> Callable[..., jax.Array]:
    """`function` of arrays, run one batch element at a time under vmap on CPU (batched
    elsewhere). Why: jaxlib's batched LAPACK kernels on CPU split a batch over XLA's intra-op
    thread pool and wait for it from inside that pool, and two of them at once waited for each
    other for ever on 2 cores (Gauss-Newton's voltages and Jacobians of 4 frames in one call,
    708 triangles). The batch's spread over the pool is given up on CPU, where the host sparse
    backend is the fast one anyway; accelerators keep their batched kernels."""
    sequential = jax.custom_batching.sequential_vmap(function)
    return lambda *arrays: jax.lax.platform_dependent(*arrays, cpu=sequential, default=function)


_cholesky = _one_at_a_time_on_cpu(jnp.linalg.cholesky)


class ConjugateGradient(AbstractLinearSolver):
    """Matrix-free conjugate gradients with a Jacobi (diagonal) preconditioner, in JAX.

    For large meshes on accelerators: memory is a few vectors per right-hand side, and every
    iteration is one sparse product on the pattern. Each column of the right-hand side runs
    until its relative residual ||b - A x|| / ||b|| is below `relative_tolerance` (default:
    1e-12 in float64, 1e-6 in float32) or `max_iterations` (default: ten times the system size;
    in exact arithmetic CG needs at most the size, and rounding on thin or badly shaped
    elements can take it past twice that) is reached. A column that stops at `max_iterations` gives
    `RESULTS.linear_solve_not_converged`: with `throw=True` (the default) the solve raises (at
    run time under jit), so `measure` and `jacobian` never return an unconverged answer
    silently; with `throw=False` the code reaches `Potentials.result`. Not expected to reach
    1e-9 agreement with the direct backends at extreme conductivity contrast (slow convergence).

    Attributes:
        relative_tolerance: The relative residual at which a column stops (static); None for
            1e-12 in float64, 1e-6 in float32.
        max_iterations: The most iterations (static); None for ten times the system size.
        throw: Raise for a solve that does not converge (static, default True).
    """

    relative_tolerance: float | None = eqx.field(static=True, default=None)
    max_iterations: int | None = eqx.field(static=True, default=None)
    throw: bool = eqx.field(static=True, default=True)

    def factorise(self, pattern: SparsityPattern, values: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The values and the Jacobi preconditioner: nothing is factorised.

        Arguments:
            pattern: The sparsity pattern; it must hold every diagonal entry.
            values: (nnz,) the matrix entries.

        Returns:
            (the (nnz,) values, the (n, 1) inverse of the diagonal).

        Raises:
            ValueError: When the pattern lacks diagonal entries.
        """
        return values, (1.0 / values[pattern.diagonal_slots])[:, None]

    def solve_factorised(
        self, pattern: SparsityPattern, factor: tuple[jax.Array, jax.Array], rhs: jax.Array
    ) -> tuple[jax.Array, RESULTS]:
        """Preconditioned conjugate gradients from zero, every column of `rhs` at once.

        Arguments:
            pattern: The sparsity pattern.
            factor: The output of `factorise`.
            rhs: (n, k) the right-hand sides B.

        Returns:
            (X ~ A^-1 B, (n, k), in the dtype of `rhs`; `RESULTS.linear_solve_not_converged`
            when a column reached `max_iterations`, `RESULTS.nonfinite` for a non-finite X,
            else `RESULTS.successful`).

        Raises:
            equinox.EquinoxRuntimeError: With `throw=True`, for a result other than
                `RESULTS.successful` (at run time under jit).
        """
        values, inverse_diagonal = factor
        dtype = values.dtype
        b = rhs.astype(dtype)
        tolerance = self.relative_tolerance
        if tolerance is None:
            tolerance = 1e-12 if dtype == jnp.float64 else 1e-6
        max_iterations = 10 * pattern.size if self.max_iterations is None else self.max_iterations
        threshold = (tolerance * jnp.linalg.norm(b, axis=0)) ** 2

        def step(state):
            x, r, p, rz, k = state
            ap = pattern.matvec(values, p)
            # Columns that have converged stop moving (their step is zero), so the result does
            # not depend on how long the slowest column of a batch runs.
            active = jnp.sum(r * r, axis=0) > threshold
            alpha = jnp.where(active, rz / jnp.sum(p * ap, axis=0), 0.0)
            x = x + alpha * p
            r = r - alpha * ap
            z = inverse_diagonal * r
            rz_next = jnp.sum(r * z, axis=0)
            p = z + jnp.where(active, rz_next / rz, 0.0) * p
            return x, r, p, jnp.where(active, rz_next, rz), k + 1

        def unconverged(r: jax.Array) -> jax.Array:
            return jnp.any(jnp.sum(r * r, axis=0) > threshold)

        def unfinished(state):
            _x, r, _p, _rz, k = state
            return (k < max_iterations) & unconverged(r)

        z = inverse_diagonal * b
        state = (jnp.zeros_like(b), b, z, jnp.sum(b * z, axis=0), 0)
        x, r, *_ = jax.lax.while_loop(unfinished, step, state)
        result = RESULTS.where(unconverged(r), RESULTS.linear_solve_not_converged, _finite_result(x))
        if self.throw:
            x = result.error_if(x, result != RESULTS.successful)
        return x.astype(rhs.dtype), result


def solver_named(name: str) -> AbstractLinearSolver:
    """The backend called `name`, with its default settings.

    Arguments:
        name: "host_sparse" (`HostSparse`), "dense_cholesky" (`DenseCholesky`) or
            "conjugate_gradient" (`ConjugateGradient`).

    Returns:
        A new instance of the backend.

    Raises:
        ValueError: For any other name.
    """
    backends = {"host_sparse": HostSparse, "dense_cholesky": DenseCholesky, "conjugate_gradient": ConjugateGradient}
    if name not in backends:
        raise ValueError(f"unknown solver {name!r}; choose one of {sorted(backends)}")
    return backends[name]()


def _finite_result(x: jax.Array) -> RESULTS:
    return RESULTS.where(jnp.all(jnp.isfinite(x)), RESULTS.successful, RESULTS.nonfinite)


def solve_spd(
    pattern: SparsityPattern,
    values: jax.Array,
    rhs: jax.Array,
    solver: AbstractLinearSolver,
) -> jax.Array:
    """X = A^-1 B for the symmetric positive definite A with `values` on `pattern`.

    Differentiable in `values` and `rhs`, in forward and reverse mode: the derivative of the
    solution is another solve with the same matrix (A is symmetric, so the transposed solve
    is the solve), and it reuses the factorisation: the solver factorises once. `rhs` has
    shape (n,) or (n, k). `solve_spd_with_result` also returns the solve's result code.

    A solver that throws (`ConjugateGradient` by default) raises for an unconverged solve: on
    concrete inputs at the call (`equinox.EquinoxRuntimeError`), under an outer `jax.jit` at run
    time, where JAX reports it when an output is read.

    Arguments:
        pattern: The sparsity pattern of A.
        values: (nnz,) the entries of A on `pattern`.
        rhs: (n,) or (n, k) B.
        solver: The backend.

    Returns:
        X, the shape of `rhs`.

    Raises:
        equinox.EquinoxRuntimeError: From a throwing solver whose solve failed.
    """
    if is_concrete(values) and is_concrete(rhs):
        return _solve_spd_at_call(pattern, values, rhs, solver)[0]
    return solve_spd_with_result(pattern, values, rhs, solver)[0]


def solve_spd_with_result(
    pattern: SparsityPattern,
    values: jax.Array,
    rhs: jax.Array,
    solver: AbstractLinearSolver,
) -> tuple[jax.Array, RESULTS]:
    """`solve_spd` with the backend's verdict: X and the `RESULTS` code of the solve.

    For the callers that report the code (`ForwardModel.potentials`). Differentiable as
    `solve_spd` is; under a throwing solver a failed solve raises at run time.

    Arguments:
        pattern: The sparsity pattern of A.
        values: (nnz,) the entries of A on `pattern`.
        rhs: (n,) or (n, k) B.
        solver: The backend.

    Returns:
        (X, the shape of `rhs`; the `RESULTS` code of the solve).
    """
    factor = solver.factorise(pattern, jax.lax.stop_gradient(values))

    def matvec(x: jax.Array) -> jax.Array:
        return pattern.matvec(values, x)

    def solve(_matvec, b: jax.Array) -> tuple[jax.Array, RESULTS]:
        columns = b if b.ndim == 2 else b[:, None]
        x, result = solver.solve_factorised(pattern, factor, columns)
        return (x if b.ndim == 2 else x[:, 0]), result

    return jax.lax.custom_linear_solve(matvec, rhs, solve, symmetric=True, has_aux=True)


# JAX dispatches asynchronously: a plain compiled call can return before its run-time checks
# (equinox.error_if) have run, and its error then surfaces only where an output is read, or never.
# equinox.filter_jit waits for them, so a concrete call raises at the call, in every process.
_solve_spd_at_call = eqx.filter_jit(solve_spd_with_result)


def relative_residual(pattern: SparsityPattern, values: jax.Array, x: jax.Array, rhs: jax.Array) -> jax.Array:
    """The relative residual ||A x - b|| / ||b|| per right-hand side.

    Arguments:
        pattern: The sparsity pattern of A.
        values: (nnz,) the entries of A.
        x: (n,) or (n, k) a solution.
        rhs: b, the shape of `x`.

    Returns:
        () or (k,): one per column of `rhs` (or for the single vector).
    """
    residual = pattern.matvec(values, x) - rhs
    return jnp.linalg.norm(residual, axis=0) / jnp.linalg.norm(rhs, axis=0)


def backward_error(pattern: SparsityPattern, values: jax.Array, x: jax.Array, rhs: jax.Array) -> jax.Array:
    """The componentwise backward error max_i |b - A x|_i / (|A| |x| + |b|)_i per right-hand side.

    Oettli-Prager (SuperLU's and LAPACK's BERR): the smallest relative change of the entries
    of A and b that makes x exact. A backward-stable solve gives a few times machine epsilon
    whatever the conditioning, where the relative residual can be large merely because the
    entries of A span many decades. Rows where |A| |x| + |b| is zero count as zero.

    Arguments:
        pattern: The sparsity pattern of A.
        values: (nnz,) the entries of A.
        x: (n,) or (n, k) a solution.
        rhs: b, the shape of `x`.

    Returns:
        () or (k,): one per column of `rhs` (or for the single vector).
    """
    residual = jnp.abs(pattern.matvec(values, x) - rhs)
    scale = pattern.matvec(jnp.abs(values), jnp.abs(x)) + jnp.abs(rhs)
    return jnp.max(jnp.where(scale > 0, residual / jnp.where(scale > 0, scale, 1), 0), axis=0)
