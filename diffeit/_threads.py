"""diffeit's host-side linear algebra (NumPy, SciPy, SuperLU) on one BLAS thread.

Why: NumPy and SciPy each load an OpenBLAS of their own, and an OpenBLAS worker thread
busy-waits for about 2^28 cycles (0.1 s) after every threaded call before it sleeps. diffeit
alternates XLA computations, SciPy's sparse solves (inside XLA callbacks) and NumPy products
of 208 x E matrices within milliseconds, so on a machine with few cores the spinning workers of
one pool hold the cores the next call needs: a one-step set-up that takes 40 ms took 40 to
800 ms on 2 cores, erratically (measured with `OPENBLAS_THREAD_TIMEOUT=4`, which shortens the
spin and removes the slowdown, and with XLA single-threaded, which does not). The products
here are small (M = 208 rows): one thread loses little, and XLA's own thread pool keeps the
large ones parallel.

`one_blas_thread` limits every loaded BLAS to one thread while diffeit computes (the libraries
found by threadpoolctl) and restores the user's setting when the outermost use ends: the
process's setting is untouched outside diffeit's calls. Nested and concurrent uses (XLA runs
callbacks on its own threads) share one limit, counted under a lock, so the setting is changed
once and restored once, possibly by another thread than the one that changed it. threadpoolctl
lets only one "controlling" thread change OpenBLAS and silently ignores the others; so the
count here decides, and each change releases that control again, leaving the user's own
threadpoolctl calls (from any thread) in charge as before.

XLA's own linear algebra on CPU (Cholesky, triangular solves, eigendecompositions) calls the
LAPACK and BLAS of SciPy's OpenBLAS too, from inside compiled code that a user may call under
a `jax.jit` of their own: `one_blas_thread_in_xla` brackets such a computation with two
callbacks that take and release the same limit (a dense Cholesky solve on 433 unknowns: 300 ms
with 2 threads beside XLA's, 2 ms on one).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, ParamSpec, TypeVar

import jax
import numpy as np
from threadpoolctl import ThreadpoolController

_lock = threading.Lock()
_depth = 0
_original_threads: list[int] = []
_controller: ThreadpoolController | None = None

P = ParamSpec("P")
R = TypeVar("R")


def _blas_controller() -> ThreadpoolController:
    """The loaded BLAS libraries, found once (finding them costs about 2 ms; limiting them
    with a known controller about 20 us). diffeit imports NumPy and SciPy's linear algebra
    before any call, so every BLAS it uses is loaded by then."""
    global _controller
    if _controller is None:
        _controller = ThreadpoolController().select(user_api="blas")
    return _controller


def _set_threads(counts: list[int]) -> None:
    """Set each BLAS's thread count from whichever thread runs this (the caller holds `_lock`)."""
    for library, count in zip(_blas_controller().lib_controllers, counts, strict=True):
        release = getattr(library, "clear_controlling_thread", None)  # threadpoolctl >= 3.5, OpenBLAS
        if release is not None:
            release()
        library.set_num_threads(count)
        if release is not None:
            release()


def _take() -> None:
    global _depth, _original_threads
    with _lock:
        if _depth == 0:
            _original_threads = [library.get_num_threads() for library in _blas_controller().lib_controllers]
            _set_threads([1] * len(_original_threads))
        _depth += 1


def _release() -> None:
    global _depth
    with _lock:
        _depth -= 1
        if _depth == 0:
            _set_threads(_original_threads)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with every BLAS limited to one thread; restore on leaving the outermost."""
    _take()
    try:
        yield
    finally:
        _release()


def host_algebra(function: Callable[P, R]) -> Callable[P, R]:
    """Decorate a function whose work is host-side linear algebra: it runs in
    `one_blas_thread`."""

    @functools.wraps(function)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        with one_blas_thread():
            return function(*args, **kwargs)

    return wrapped


def one_blas_thread_in_xla(function: Callable[[jax.Array], Any]) -> Callable[[jax.Array], Any]:
    """Wrap a JAX function of one floating array whose compiled code calls LAPACK or BLAS (a
    Cholesky factorisation, triangular solves): on CPU a callback takes the one-thread limit
    before it runs and another releases it after, ordered by data dependence (the argument
    waits for the first, the second waits for every floating output); on other platforms the
    function runs as it is. Works under jit, vmap and differentiation (the callbacks see
    values through `stop_gradient` and add exact zeros). A computation that aborts between the
    two callbacks leaves the limit in place."""

    def bracketed(x: jax.Array) -> Any:
        gate = _callback(_take, x)
        result = function(x + gate)
        leaves, structure = jax.tree_util.tree_flatten(result)
        floating = [i for i, leaf in enumerate(leaves) if jax.numpy.issubdtype(leaf.dtype, jax.numpy.floating)]
        probe = sum(leaves[i].reshape(-1)[0] for i in floating)
        leaves[floating[0]] = leaves[floating[0]] + _callback(_release, probe).astype(leaves[floating[0]].dtype)
        return jax.tree_util.tree_unflatten(structure, leaves)

    def wrapped(x: jax.Array) -> Any:
        return jax.lax.platform_dependent(x, cpu=bracketed, default=function)

    return wrapped


def _callback(action: Callable[[], None], x: jax.Array) -> jax.Array:
    """Zeros shaped like the first entry of `x`, once `action` has run on the host."""
    probe = jax.lax.stop_gradient(x.reshape(-1)[0])

    def host(value: np.ndarray) -> np.ndarray:
        action()
        return np.zeros_like(value)

    # expand_dims: under vmap the batch arrives in one call, so the limit is taken once.
    return jax.pure_callback(host, jax.ShapeDtypeStruct(probe.shape, probe.dtype), probe, vmap_method="expand_dims")
