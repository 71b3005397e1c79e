"""Array helpers shared by the modules of diffeit."""

import jax
import numpy as np


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`: meshes and protocols never change after construction."""
    array = np.array(array)
    array.setflags(write=False)
    return array


def is_concrete(x) -> bool:
    """Whether `x` holds values (not a tracer under jit, vmap or grad): values are checked
    with messages naming the offenders only then."""
    return not isinstance(x, jax.core.Tracer)
