"""EIDORS-style MATLAB files of adjacent-drive frames."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from .._messages import name_indices
from ..protocol import adjacent, from_full_layout, to_full_layout
from ._recording import Recording


def read_eidors_mat(
    path: str | os.PathLike,
    variable: str | None = None,
    *,
    reference: str | None = None,
    n_electrodes: int = 16,
    frame_rate: float = 1.0,
    strict: bool = False,
) -> Recording | dict[str, Recording]:
    """Adjacent-drive frames from a MATLAB .mat file as EIDORS data sets store them.

    Each variable holds frames of either layout, which are read into `adjacent(n_electrodes)`
    (16 electrodes: 208 readings, EIDORS's `mk_stim_patterns(16,1,'{ad}','{ad}',
    {'no_meas_current'},1)` order):

    - the full n x n layout (256 values): value n * k + m is drive k, pair (m, m+1), with zeros
      where the pair touches electrode k or k+1 (see `diffeit.protocol.to_full_layout`);
    - n(n-3) values (208), already in adjacent order.

    Orientation: EIDORS stores one frame per matrix column (the Montreal set: (256, T)), so
    a matrix whose first dimension has a frame's length is read column by column; otherwise
    one whose second dimension has it is read row by row (a (256, 256) matrix is taken as
    columns). A vector is one frame.

    Driven pairs: the 3n values on pairs that touch a driven electrode are dropped. EIDORS
    data hold zeros there, but some sets record a reading (the Montreal stomach frames hold
    values of the order of the largest readings: the voltage across the contact impedance). So
    non-zero driven-pair values are accepted and dropped (`provenance["metadata"]
    ["driven_pair_values"]` says which), unless `strict=True`, which refuses them. What is
    refused always: non-zero driven pairs together with readings that are zero in every frame,
    as that means zeros sit elsewhere: a different layout (rotated measurements, another drive).

    **Arguments:**

    - `path`: the .mat file (MATLAB v4 to v7.2, what `scipy.io.loadmat` reads).
    - `variable`: the variable to read; None reads every variable holding frames (others,
      such as ECG traces, are skipped).
    - `reference`: a variable holding one frame, the reference of every recording returned.
    - `n_electrodes`: electrodes of the adjacent protocol.
    - `frame_rate`: frames per second; the files carry no times, so frame t is at
      t / frame_rate seconds (the Montreal sets: 7 frames/s).
    - `strict`: refuse frames whose driven-pair values are not zero.

    **Returns:** a `Recording` (float64 frames, no mesh, `voltage_unit="arbitrary"`: EIDORS
    files store device units, the Montreal sets ADC magnitudes), or with `variable=None` a dict
    of them by variable name.

    **Raises:** `FileNotFoundError` for a missing file; `ValueError` naming the file and the
    problem for an unreadable file, an unknown variable, a shape of neither layout, non-finite
    or complex values, a misplaced layout, a reference of more than one frame.
    """
    path = Path(path)
    if not math.isfinite(frame_rate) or frame_rate <= 0:
        raise ValueError(f"frame_rate must be positive (frames per second); got {frame_rate}")
    if not path.exists():
        raise FileNotFoundError(f"no such .mat file: {path}")
    try:
        contents = scipy.io.loadmat(path)
    except (ValueError, TypeError, NotImplementedError, OSError) as error:
        raise ValueError(f"{path} is not a MATLAB file scipy can read (v7.3 files are HDF5): {error}") from None
    arrays = {name: value for name, value in contents.items() if not name.startswith("__")}
    sizes = (n_electrodes * n_electrodes, n_electrodes * (n_electrodes - 3))

    def load(name: str) -> tuple[np.ndarray, dict[str, Any]]:
        if name not in arrays:
            raise ValueError(f"{path} has no variable {name!r}; it has {_describe(arrays)}")
        try:
            return _adjacent_frames(arrays[name], n_electrodes, strict)
        except ValueError as error:
            raise ValueError(f"{path}, variable {name!r}: {error}") from None

    reference_frame = None
    if reference is not None:
        reference_frames, _ = load(reference)
        if len(reference_frames) != 1:
            raise ValueError(
                f"{path}, variable {reference!r} holds {len(reference_frames)} frames; a reference is one frame"
            )
        reference_frame = reference_frames[0]
    if variable is None:
        names = [name for name, value in arrays.items() if _holds_frames(value, sizes)]
        if not names:
            raise ValueError(f"{path} holds no variable of {sizes[0]}- or {sizes[1]}-value frames: {_describe(arrays)}")
    else:
        names = [variable]
    recordings = {}
    for name in names:
        frames, details = load(name)
        recordings[name] = Recording(
            frames=frames,
            times=np.arange(len(frames)) / frame_rate,
            protocol=adjacent(n_electrodes),
            reference=reference_frame,
            provenance={
                "source": f"EIDORS .mat file {path.name}, variable {name}",
                "metadata": {
                    "file": str(path),
                    "variable": name,
                    "reference_variable": reference,
                    "frame_rate": frame_rate,
                    **details,
                },
            },
            voltage_unit="arbitrary",
        )
    return recordings if variable is None else recordings[variable]


def _adjacent_frames(value: Any, n: int, strict: bool) -> tuple[np.ndarray, dict[str, Any]]:
    """(T, n(n-3)) adjacent frames of a variable, and how they were laid out."""
    full, short = n * n, n * (n - 3)
    array = np.asarray(value)
    if np.iscomplexobj(array):
        raise ValueError("holds complex values; take the magnitude or the real part first")
    if not np.issubdtype(array.dtype, np.number):
        raise ValueError(f"holds {array.dtype} values, not numbers")
    array = array.astype(np.float64)
    if array.ndim == 1 or (array.ndim == 2 and 1 in array.shape):
        array, orientation = array.reshape(1, -1), "one frame"
    elif array.ndim == 2 and array.shape[0] in (full, short):
        array, orientation = array.T, "columns are frames"
    else:
        orientation = "rows are frames"
    if array.ndim != 2 or array.shape[1] not in (full, short):
        raise ValueError(f"has shape {np.shape(value)}; frames of {n} electrodes have {full} or {short} values")
    if not np.all(np.isfinite(array)):
        bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
        raise ValueError(f"frames {name_indices(bad)} hold non-finite values")
    if array.shape[1] == short:
        return array, {"layout": f"adjacent, {short} values", "orientation": orientation}
    driven = to_full_layout(np.ones(short), n) == 0  # the 3n places of pairs touching a driven electrode
    zero_driven = not np.any(array[:, driven])
    if not zero_driven:
        silent = np.flatnonzero(~np.any(array, axis=0) & ~driven)
        if len(silent):
            raise ValueError(
                f"values {name_indices(silent)} are zero in every frame but the pairs touching driven electrodes "
                f"(values {name_indices(np.flatnonzero(driven))}) are not: these frames are not in the "
                f"{n} x {n} adjacent layout (value {n} * drive + m, pair (m, m+1), measurements from m = 0)"
            )
        if strict:
            frames = np.flatnonzero(np.any(array[:, driven], axis=1))
            raise ValueError(
                f"frames {name_indices(frames)} hold non-zero values on pairs touching driven electrodes "
                "(strict=True refuses them; without it they are dropped)"
            )
    details = {
        "layout": f"{n} x {n} with zeros at pairs touching driven electrodes (EIDORS)",
        "orientation": orientation,
        "driven_pair_values": "zero" if zero_driven else "non-zero, dropped",
    }
    return np.asarray(from_full_layout(array, n)), details


def _holds_frames(value: Any, sizes: tuple[int, int]) -> bool:
    array = np.asarray(value)
    return np.issubdtype(array.dtype, np.number) and array.ndim in (1, 2) and bool(set(array.shape) & set(sizes))


def _describe(arrays: dict[str, Any]) -> str:
    return ", ".join(f"{name} {np.shape(value)}" for name, value in arrays.items()) or "no variables"
