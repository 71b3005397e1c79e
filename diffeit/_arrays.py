"""Array helpers for the immutable data classes of diffeit."""

import numpy as np


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`: meshes and protocols never change after construction."""
    array = np.array(array)
    array.setflags(write=False)
    return array
