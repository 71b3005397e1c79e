"""How diffeit gets float64 from JAX without changing a program that merely imports it.

JAX computes in float32 unless `jax_enable_x64` is on. EIT data are small differences of
voltages that span orders of magnitude, so diffeit's models compute in float64 by default.
`import diffeit` changes no setting. Building a forward model (which every simulation and
reconstruction does), or computing with the memory model on images without one
(`diffeit.memory.integrate_memory`, `diffeit.fit.memory`, `memory_from_presses`,
`correct_memory`), turns `jax_enable_x64` on if it is off, once, and says so with a
`PrecisionWarning`; a program that sets it first (`jax.config.update("jax_enable_x64", True)`,
as diffeit's command line, tests and benchmarks do) sees no warning. Float32 stays available
per call: pass float32 arrays.
"""

import threading
import warnings

import jax


class PrecisionWarning(UserWarning):
    """A precision matter: diffeit turned on JAX's float64, or a float32 computation whose
    voltages are estimated to be off by more than 1e-3."""


_lock = threading.Lock()


def ensure_float64() -> None:
    """Turn on `jax_enable_x64` if it is off, warning once that diffeit did so."""
    if jax.config.read("jax_enable_x64"):
        return
    with _lock:
        if jax.config.read("jax_enable_x64"):
            return
        jax.config.update("jax_enable_x64", True)
    warnings.warn(
        "diffeit turned on 64-bit floats in JAX (jax_enable_x64) for this process: its forward model computes "
        "in float64, and arrays made before this point are float32. Call "
        'jax.config.update("jax_enable_x64", True) before using diffeit to make this explicit and silence '
        "this warning.",
        PrecisionWarning,
        stacklevel=3,
    )
