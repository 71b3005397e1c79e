"""EIDORS-style MATLAB files of adjacent-drive frames."""

from __future__ import annotations

import io
import math
import os
import struct
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

from .._messages import name_indices
from ..protocol import adjacent, from_full_layout, to_full_layout
from ._recording import READINGS, Recording

COMPLEX_PARTS = ("real", "magnitude")
DRIVEN_READINGS = ("auto", "keep", "drop")


def read_eidors_mat(
    path: str | os.PathLike,
    variable: str | None = None,
    *,
    reference: str | None = None,
    n_electrodes: int = 16,
    frame_rate: float = 1.0,
    strict: bool = False,
    complex_part: str = "real",
    driven_readings: str = "auto",
    readings: str | None = None,
) -> Recording | dict[str, Recording]:
    """Adjacent-drive frames from a MATLAB .mat file as EIDORS data sets store them.

    Each variable holds frames of either layout: the full n x n layout (256 values for 16
    electrodes; value n * k + m is drive k (in at k+1, out at k), pair (m, m+1), U_m - U_(m+1),
    with zeros where the pair touches a driven electrode unless the system measured there),
    which is `adjacent(n, measure_driven=True)`'s order and sign (see
    `diffeit.protocol.to_full_layout`); or n(n-3) values (208), `adjacent(n)`'s order and sign
    (EIDORS's `mk_stim_patterns(16, 1, '{ad}', '{ad}', {'no_meas_current'}, 1)`). A matrix
    whose first dimension has a frame's length is read column by column (EIDORS's one frame per
    column; a (256, 256) matrix too), otherwise one whose second dimension has it row by row; a
    vector is one frame. The layouts, complex values, the driven pairs and what the reader can
    and cannot detect of a damaged file are in
    docs/tutorials/real-recordings.md#what-the-readers-check.

    Arguments:
        path: The .mat file (MATLAB v4 to v7.2, what `scipy.io.loadmat` reads; v7.3 files,
            HDF5, are refused: save with '-v7').
        variable: The variable to read; None reads every variable holding frames (others,
            such as ECG traces, are skipped).
        reference: A variable holding one frame, the reference of every recording returned.
        n_electrodes: Electrodes of the adjacent protocol.
        frame_rate: Frames per second; the files carry no times, so frame t is at
            t / frame_rate seconds (the Montreal sets: 7 frames/s).
        strict: With the driven pairs dropped, refuse frames whose driven-pair values are not
            zero.
        complex_part: How complex values are read: "real" (default, the in-phase part) or
            "magnitude" (|V|, read as `readings="magnitude"`).
        driven_readings: The 3n readings on pairs that touch a driven electrode: "auto"
            (default) keeps them (protocol `adjacent(n, measure_driven=True)`, n * n readings)
            when every one is non-zero in every frame of the variable and of the reference,
            and drops them otherwise (protocol `adjacent(n)`); "keep" keeps them (refusing a
            variable or reference that holds none: n(n-3) values or zeros throughout); "drop"
            drops them, accepting non-zero values there unless `strict=True`.
        readings: "signed", "magnitude", or None (default) to decide from the values:
            "magnitude" when complex values are read as magnitudes or when every value of the
            variable and the reference, as read, is >= 0; "signed" otherwise (see `Recording`).

    Returns:
        A `Recording` (float64 frames, no mesh, `voltage_unit="arbitrary"`: EIDORS files
        store device units, the Montreal sets ADC magnitudes), or with `variable=None` a dict
        of them by variable name. `provenance["metadata"]` records the layout, orientation,
        `complex_part` (None for real values), `driven_pair_values` ("zero", "non-zero" or
        "some zero"; absent for n(n-3) values) and `driven_readings` ("kept", "dropped", or
        "absent" for n(n-3) values).

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file and the problem, for an unreadable or damaged file, an
            unknown variable or one that is not numeric, a shape of neither layout, non-finite
            values, a misplaced layout (non-zero driven pairs together with readings that are
            zero in every frame), a reference of more than one frame, driven readings to keep
            that are not there, negative values read as magnitudes; and for an option out of
            range (frame rate, `complex_part`, `driven_readings`, `readings`).
    """
    path = Path(path)
    if not math.isfinite(frame_rate) or frame_rate <= 0:
        raise ValueError(f"frame_rate must be positive (frames per second); got {frame_rate}")
    for name, value, allowed in (
        ("complex_part", complex_part, COMPLEX_PARTS),
        ("driven_readings", driven_readings, DRIVEN_READINGS),
        ("readings", readings, (None, *READINGS)),
    ):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}; got {value!r}")
    if not path.is_file():
        raise FileNotFoundError(f"no such .mat file: {path}")
    arrays, others = _load_mat(path)
    n = n_electrodes
    sizes = (n * n, n * (n - 3))

    def load(name: str) -> tuple[np.ndarray, bool, dict[str, Any]]:
        if name in others:
            raise ValueError(f"{path}, variable {name!r} is {others[name]}, not frames")
        if name not in arrays:
            raise ValueError(f"{path} has no variable {name!r}; it has {_describe(arrays, others)}")
        try:
            return _file_frames(arrays[name], n, complex_part)
        except ValueError as error:
            raise ValueError(f"{path}, variable {name!r}: {error}") from None

    reference_values, reference_complex = None, False
    if reference is not None:
        reference_values, reference_complex, _ = load(reference)
        if len(reference_values) != 1:
            raise ValueError(
                f"{path}, variable {reference!r} holds {len(reference_values)} frames; a reference is one frame"
            )
    if variable is None:
        names = [name for name, value in arrays.items() if _holds_frames(value, sizes)]
        if not names:
            raise ValueError(
                f"{path} holds no variable of {sizes[0]}- or {sizes[1]}-value frames: {_describe(arrays, others)}"
            )
    else:
        names = [variable]
    recordings = {}
    for name in names:
        values, is_complex, details = load(name)
        parts = {"the frames": values}  # what a message calls each array: values
        if reference_values is not None:
            parts[f"the reference {reference!r}"] = reference_values
            is_complex = is_complex or reference_complex
        try:
            keep = _keep_driven(parts, n, driven_readings)
            if strict and not keep:
                _refuse_driven_values(parts, n)
        except ValueError as error:
            raise ValueError(f"{path}, variable {name!r}: {error}") from None
        frames, reference_frame = (_in_protocol(v, n, keep) for v in (values, reference_values))
        chosen = readings
        if chosen is None:
            magnitudes = is_complex and complex_part == "magnitude"
            chosen = "magnitude" if magnitudes or all(np.all(v >= 0) for v in parts.values()) else "signed"
        try:
            recordings[name] = Recording(
                frames=frames,
                times=np.arange(len(frames)) / frame_rate,
                protocol=adjacent(n, measure_driven=keep),
                reference=None if reference_frame is None else reference_frame[0],
                provenance={
                    "source": f"EIDORS .mat file {path.name}, variable {name}",
                    "metadata": {
                        "file": str(path),
                        "variable": name,
                        "reference_variable": reference,
                        "frame_rate": frame_rate,
                        **details,
                        "complex_part": complex_part if is_complex else None,
                        "driven_readings": "kept" if keep else "dropped" if values.shape[1] == n * n else "absent",
                    },
                },
                voltage_unit="arbitrary",
                readings=chosen,
            )
        except ValueError as error:
            raise ValueError(f"{path}, variable {name!r}: {error}") from None
    return recordings if variable is None else recordings[variable]


def _load_mat(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The numeric variables of a MATLAB file by name, as scipy reads them, and the names of
    the others (cells, structs, text, sparse matrices, objects: never read) with what they are;
    ValueError naming the file for anything unreadable."""
    data = path.read_bytes()
    if len(data) < 4:
        raise ValueError(f"{path} is not a MATLAB file: {len(data)} bytes")
    others: dict[str, str] = {}
    if 0 not in data[:4]:  # scipy's rule: v4 files have a zero in their first four bytes, v5 and v7.3 none
        try:
            data, others = _checked_mat5(data)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
    # From memory: a damaged length cannot make scipy allocate or wait for bytes the file lacks.
    # Its warnings ("returned data may be corrupt") are errors.
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            contents = scipy.io.loadmat(io.BytesIO(data))
    except Exception as error:  # scipy's v4 reader raises many kinds on a damaged file (IndexError, ...)
        raise ValueError(f"{path} is not a MATLAB file scipy can read: {type(error).__name__}: {error}") from None
    arrays = {name: value for name, value in contents.items() if not name.startswith("__")}
    for name, value in arrays.items():
        if isinstance(value, str):  # scipy's stand-in for a variable it could not read
            raise ValueError(f"{path}, variable {name!r} is unreadable: {value}")
    return arrays, others


# MAT v5 ("MAT-File Format", MathWorks): a 128-byte header (the version at bytes 124-125 and
# the byte order at 126-127: "IM" little-endian, "MI" big-endian), then one element per
# variable: an 8-byte tag (data type, byte count), then its bytes. A variable is an miMATRIX
# element, a sequence of elements (array flags, dimensions, name, then by class: the real and
# imaginary values; cells, fields) each padded to 8 bytes, a small one (at most 4 bytes)
# packed into its tag; or an miCOMPRESSED element, a zlib stream (checksummed) of an miMATRIX.
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED, _MI_UTF8 = 1, 5, 6, 14, 15, 16
# Bytes per value of the numeric data types, miINT8 .. miDOUBLE, miINT64, miUINT64. scipy looks
# a data type up in a table without bounds: any other type in a damaged file is a segmentation
# fault (scipy 1.17), so only numeric variables whose every element is checked are given to it.
_VALUE_SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 9: 8, 12: 8, 13: 8}
_NUMERIC_CLASSES = range(6, 16)  # mxDOUBLE_CLASS .. mxUINT64_CLASS
_CLASSES = {1: "a cell array", 2: "a struct", 3: "an object", 4: "text", 5: "a sparse matrix", 16: "a function handle"}
_OPAQUE_CLASS = 17  # a MATLAB object (e.g. a string or table): its name follows the flags, no dimensions
_COMPLEX_FLAG = 0x800


def _checked_mat5(data: bytes) -> tuple[bytes, dict[str, str]]:
    """The numeric variables of the v5 MAT file `data`, uncompressed, as a v5 file of their
    own, and the names of its other variables with what they are. ValueError for a v7.3 file
    (HDF5), a variable cut short or reaching past the file, a compressed variable whose zlib
    stream is damaged, cut short or not followed by the next variable, an element of another
    data type or size than its place in a numeric variable needs, two variables of one name."""
    if len(data) < 128:
        raise ValueError(f"cut short or not a MATLAB file: {len(data)} bytes, a v5 MAT file's header has 128")
    order = {b"IM": "<", b"MI": ">"}.get(data[126:128])
    major = data[125] if order == "<" else data[124]
    if order is None or major not in (1, 2):
        raise ValueError("not a MATLAB file: bytes 124-127 are not a v5 header's version and byte order")
    if major == 2:
        raise ValueError("a MATLAB v7.3 file (HDF5), which is not read: save it with save(..., '-v7')")
    tag = struct.Struct(order + "II")
    # No subsystem offset: the subsystem's objects are among the variables not passed on.
    parts, others, names, offset = [data[:116] + bytes(8) + data[124:128]], {}, set(), 128
    while offset < len(data):
        if len(data) - offset < tag.size:
            raise ValueError(f"cut short: the variable at byte {offset} has {len(data) - offset} of its 8 tag bytes")
        data_type, size = tag.unpack_from(data, offset)
        start, end = offset + tag.size, offset + tag.size + size
        where = f"the variable at byte {offset}"
        if data_type not in (_MI_MATRIX, _MI_COMPRESSED):
            raise ValueError(f"{where} has data type {data_type}, neither miMATRIX nor miCOMPRESSED: damaged")
        if end > len(data):
            raise ValueError(f"cut short: {where} claims {size} bytes, the file has {len(data) - start} after its tag")
        matrix = _decompressed(data[start:end], where) if data_type == _MI_COMPRESSED else data[offset:end]
        name, kind = _variable(matrix, tag, where)
        if name in names:
            raise ValueError(f"two variables are named {name!r}: damaged")
        names.add(name)
        if kind is None:
            parts.append(matrix)
        else:
            others[name] = kind
        offset = end
    return b"".join(parts), others


def _decompressed(stream: bytes, where: str) -> bytes:
    """The bytes of a compressed variable: one whole zlib stream, its checksum valid, nothing after it."""
    decompressor = zlib.decompressobj()
    try:
        matrix = decompressor.decompress(stream) + decompressor.flush()
    except zlib.error as error:
        raise ValueError(f"{where} is compressed and damaged: {error}") from None
    if not decompressor.eof:
        raise ValueError(f"{where} is compressed and cut short: its zlib stream does not end")
    if decompressor.unused_data:
        raise ValueError(f"{where} is compressed and followed by {len(decompressor.unused_data)} bytes of no variable")
    return matrix


def _variable(matrix: bytes, tag: struct.Struct, where: str) -> tuple[str, str | None]:
    """The name of the variable in the miMATRIX element `matrix`, and None if it is a numeric
    array, checked whole (what scipy is given), else what it is (its header checked only)."""
    if len(matrix) < tag.size or tag.unpack_from(matrix) != (_MI_MATRIX, len(matrix) - tag.size):
        raise ValueError(f"{where} is not one miMATRIX element: damaged")
    elements = _elements(matrix, tag, where)
    flags_type, flags = next(elements, (None, b""))
    if flags_type != _MI_UINT32 or len(flags) != 8:
        raise ValueError(f"{where} has no array flags (8 bytes of miUINT32): damaged")
    (flags_class,) = struct.unpack(tag.format[0] + "I", flags[:4])
    matrix_class = flags_class & 0xFF
    if matrix_class == _OPAQUE_CLASS:
        return _name(next(elements, (None, b"")), where), "an object"
    dims_type, dims_bytes = next(elements, (None, b""))
    if dims_type not in (_MI_INT32, _MI_UINT32) or len(dims_bytes) % 4 or not 2 <= len(dims_bytes) // 4 <= 32:
        raise ValueError(f"{where} has no dimensions (2 to 32 miINT32 values): damaged")
    dims = struct.unpack(f"{tag.format[0]}{len(dims_bytes) // 4}i", dims_bytes)
    name = _name(next(elements, (None, b"")), where)
    if min(dims) < 0:
        raise ValueError(f"{where} ({name!r}) has negative dimensions {dims}: damaged")
    if matrix_class not in _NUMERIC_CLASSES:
        return name, _CLASSES.get(matrix_class, f"of unknown class {matrix_class}")
    parts = ("real", "imaginary") if flags_class & _COMPLEX_FLAG else ("real",)
    for part in parts:
        data_type, values = next(elements, (None, b""))
        if data_type not in _VALUE_SIZES or len(values) != math.prod(dims) * _VALUE_SIZES[data_type]:
            raise ValueError(
                f"{where} ({name!r}, {'x'.join(map(str, dims))}) has no {part} values of that size (data type "
                f"{data_type}, {len(values)} bytes): damaged"
            )
    if next(elements, None) is not None:
        raise ValueError(f"{where} ({name!r}) holds elements after its values: damaged")
    return name, None


def _name(element: tuple[int | None, bytes], where: str) -> str:
    data_type, name = element
    if data_type not in (_MI_INT8, _MI_UTF8):
        raise ValueError(f"{where} has no name (miINT8 characters): damaged")
    return name.decode("latin-1")


def _elements(matrix: bytes, tag: struct.Struct, where: str) -> Iterator[tuple[int, bytes]]:
    """(data type, bytes) of each element in an miMATRIX element, in order, each checked to lie within it."""
    position = tag.size
    while position < len(matrix):
        if len(matrix) - position < tag.size:
            raise ValueError(f"{where}: an element at byte {position} of it is cut short: damaged")
        first, size = tag.unpack_from(matrix, position)
        if first >> 16:  # a small element: byte count and data type in the first four bytes, the data in the next
            data_type, size, start, following = first & 0xFFFF, first >> 16, position + 4, position + tag.size
            if size > 4:
                raise ValueError(f"{where}: a small element at byte {position} of it claims {size} bytes: damaged")
        else:
            data_type, start = first, position + tag.size
            following = start + size + -size % 8
            if start + size > len(matrix):
                raise ValueError(f"{where}: an element at byte {position} of it claims bytes beyond it: damaged")
        yield data_type, matrix[start : start + size]
        position = following


def _file_frames(value: Any, n: int, complex_part: str) -> tuple[np.ndarray, bool, dict[str, Any]]:
    """(T, n * n or n(n-3)) real frames of a variable in the file's layout, whether the file
    held complex values, and how the frames were laid out."""
    full, short = n * n, n * (n - 3)
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.number):
        raise ValueError(f"holds {array.dtype} values, not numbers")
    if array.ndim == 1 or (array.ndim == 2 and 1 in array.shape):
        array, orientation = array.reshape(1, -1), "one frame"
    elif array.ndim == 2 and array.shape[0] in (full, short):
        array, orientation = array.T, "columns are frames"
    else:
        orientation = "rows are frames"
    if array.ndim != 2 or array.shape[1] not in (full, short):
        raise ValueError(f"has shape {np.shape(value)}; frames of {n} electrodes have {full} or {short} values")
    if not np.all(np.isfinite(array)):  # complex: either part, also the one not read
        bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
        raise ValueError(f"frames {name_indices(bad)} hold non-finite values")
    is_complex = np.iscomplexobj(array)
    if is_complex:
        array = np.abs(array) if complex_part == "magnitude" else array.real
    array = array.astype(np.float64)
    if array.shape[1] == short:
        return array, is_complex, {"layout": f"adjacent, {short} values", "orientation": orientation}
    driven = _driven(n)
    driven_values = array[:, driven]
    if np.any(driven_values):
        silent = np.flatnonzero(~np.any(array, axis=0) & ~driven)
        if len(silent):
            raise ValueError(
                f"values {name_indices(silent)} are zero in every frame but the pairs touching driven electrodes "
                f"(values {name_indices(np.flatnonzero(driven))}) are not: these frames are not in the "
                f"{n} x {n} adjacent layout (value {n} * drive + m, pair (m, m+1), measurements from m = 0)"
            )
        described = "non-zero" if np.all(driven_values) else "some zero"
    else:
        described = "zero"
    details = {
        "layout": f"{n} x {n}, value {n} * drive + m is pair (m, m+1) (EIDORS)",
        "orientation": orientation,
        "driven_pair_values": described,
    }
    return array, is_complex, details


def _driven(n: int) -> np.ndarray:
    """(n * n,) bool: the 3n places of the full layout on pairs that touch a driven electrode."""
    return np.asarray(to_full_layout(np.ones(n * (n - 3)), n)) == 0


def _keep_driven(parts: dict[str, np.ndarray], n: int, driven_readings: str) -> bool:
    """Whether to keep the driven-pair readings of the frames and the reference (`parts`, by
    what a message calls them)."""
    if driven_readings == "drop":
        return False
    if driven_readings == "auto":
        return all(array.shape[1] == n * n and np.all(array[:, _driven(n)]) for array in parts.values())
    for what, array in parts.items():
        if array.shape[1] != n * n:
            raise ValueError(
                f'{what} hold {array.shape[1]} values, no driven-pair readings to keep (driven_readings="keep")'
            )
        if not np.any(array[:, _driven(n)]):
            raise ValueError(
                f'{what} hold zeros on every driven pair: nothing was measured there to keep (driven_readings="keep"); '
                'use driven_readings="drop"'
            )
    return True


def _refuse_driven_values(parts: dict[str, np.ndarray], n: int) -> None:
    """strict: refuse non-zero values on the driven pairs that are dropped."""
    for what, array in parts.items():
        if array.shape[1] != n * n:
            continue
        frames = np.flatnonzero(np.any(array[:, _driven(n)], axis=1))
        if len(frames):
            raise ValueError(
                f"{what} hold non-zero values on pairs touching driven electrodes in frames {name_indices(frames)} "
                "(strict=True refuses them; without it they are dropped)"
            )


def _in_protocol(array: np.ndarray | None, n: int, keep: bool) -> np.ndarray | None:
    """Frames in the file's layout in the order of `adjacent(n, measure_driven=keep)`: the full
    layout is already `adjacent(n, measure_driven=True)`'s order and sign."""
    if array is None or keep or array.shape[1] == n * (n - 3):
        return array
    return np.asarray(from_full_layout(array, n))


def _holds_frames(value: Any, sizes: tuple[int, int]) -> bool:
    array = np.asarray(value)
    return np.issubdtype(array.dtype, np.number) and array.ndim in (1, 2) and bool(set(array.shape) & set(sizes))


def _describe(arrays: dict[str, Any], others: dict[str, str]) -> str:
    described = [f"{name} {np.shape(value)}" for name, value in arrays.items()]
    described += [f"{name} ({kind})" for name, kind in others.items()]
    return ", ".join(described) or "no variables"
