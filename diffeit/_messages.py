"""Wording shared by the error messages of diffeit."""

import numpy as np


def name_indices(indices: np.ndarray, limit: int = 10) -> str:
    """'[3, 7, 12, ...]': the first `limit` indices, for an error message."""
    indices = np.asarray(indices).ravel()
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return f"[{shown}{', ...' if len(indices) > limit else ''}]"
