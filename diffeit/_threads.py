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

`one_blas_thread` limits every loaded BLAS to one thread while diffeit computes, through
threadpoolctl, and restores the user's setting when the outermost use ends: the process's
setting is untouched outside diffeit's calls. Nested and concurrent uses (XLA runs callbacks on
its own threads) share one limit, counted, so the setting is restored exactly once.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, ParamSpec, TypeVar

from threadpoolctl import ThreadpoolController

_lock = threading.Lock()
_depth = 0
_active_limit: Any = None
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


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with every BLAS limited to one thread; restore on leaving the outermost."""
    global _depth, _active_limit
    with _lock:
        if _depth == 0:
            _active_limit = _blas_controller().limit(limits=1)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _active_limit.restore_original_limits()
                _active_limit = None


def host_algebra(function: Callable[P, R]) -> Callable[P, R]:
    """Decorate a function whose work is host-side linear algebra: it runs in
    `one_blas_thread`."""

    @functools.wraps(function)
    def wrapped(*args: P.args, **kwargs: P.kwargs) -> R:
        with one_blas_thread():
            return function(*args, **kwargs)

    return wrapped
