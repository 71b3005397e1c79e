"""HDF5 files that refuse damage: every diffeit file is opened and written through here.

Reading: before HDF5 sees a file, its superblock (the first bytes: format version, the writer's
open-for-writing flags, the end-of-file address) is read in Python. A file shorter than its
recorded end is truncated, and is refused at once: HDF5's own single-writer/multiple-reader
(SWMR) access would accept it and then wait for the missing bytes for ever. Only a file whose
superblock says a SWMR writer (a recorder) holds it open may still grow: it gets `GROWTH_WAIT`
seconds to reach its recorded end. Everything HDF5 raises while reading becomes a `ValueError`
naming the file.

Writing: every array dataset carries HDF5's Fletcher-32 checksum (read back with verification
on), every scalar sits in its object header (compact layout), every attribute too
(`write_attributes`: strings fixed-length, not in HDF5's global heap, which carries no
checksum), and files use the HDF5 1.10 format, whose metadata blocks carry checksums of their
own: altered bytes anywhere are detected when read, never returned as data. Files are written under a temporary name and
renamed when complete, so an interrupted write leaves nothing half-written at the path.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

# HDF5 file format 1.10 or later: metadata checksums, and what SWMR access needs.
LIBVER = "v110"
# Seconds a reader gives a file a live recorder holds to reach the end its superblock records.
GROWTH_WAIT = 1.0
# Seconds a read of a file a writer holds open is tried again when it fails (a chunk caught while
# it was rewritten: the writer finishes it within milliseconds; damage fails every time).
REREAD_WAIT = 0.5
# Seconds a reader waits while another process holds a file's lock (a recorder creating it).
LOCK_WAIT = 5.0
# Tries HDF5 gives a metadata block that fails its checksum under SWMR access (a writer may be
# rewriting it). HDF5 waits twice as long before each try, and its default of 100 tries waits
# for hours on a damaged byte; 10 tries wait about a millisecond, and `read_checked` then tries
# the whole read again for up to REREAD_WAIT seconds.
SWMR_READ_ATTEMPTS = 10

_SIGNATURE = b"\x89HDF\r\n\x1a\n"
# Where a superblock may start: 0, or after a user block of 512 bytes times a power of two.
_SUPERBLOCK_OFFSETS = (0, 512, 1024, 2048, 4096)
# File consistency flags of superblock versions 2 and 3: a writer has the file open (and in
# SWMR mode). HDF5 clears them when it closes the file; a killed writer leaves them set.
_OPEN_FOR_WRITING = 0x1
_SWMR_WRITING = 0x4


class _ReadDuringWrite(ValueError):
    """HDF5 failed reading a file that a writer holds open: perhaps damage, perhaps a chunk
    caught while it was rewritten."""


class NoChecksumWarning(UserWarning):
    """A file was read whose datasets carry no checksums (written before diffeit stored them):
    altered bytes in them cannot be detected."""


@dataclass(frozen=True)
class Superblock:
    """What the superblock of an HDF5 file says: format `version` (0-3), the writer's
    `flags`, and `end`, the byte the file must reach (its end-of-file address, absolute)."""

    version: int
    flags: int
    end: int

    @property
    def open_for_writing(self) -> bool:
        return self.version >= 2 and bool(self.flags & _OPEN_FOR_WRITING)

    @property
    def swmr_writing(self) -> bool:
        return self.version >= 3 and bool(self.flags & _SWMR_WRITING)


def read_superblock(path: Path, what: str = "HDF5 file") -> Superblock:
    """The superblock of the HDF5 file at `path`; `ValueError` naming the file when it is empty,
    not HDF5 (naming what it looks like) or its superblock is cut short or unknown."""
    with open(path, "rb") as file:
        head = file.read(_SUPERBLOCK_OFFSETS[-1] + 64)
    if not head:
        raise ValueError(f"{path} is empty, not a {what}")
    base = next((offset for offset in _SUPERBLOCK_OFFSETS if head[offset : offset + 8] == _SIGNATURE), None)
    if base is None:
        raise ValueError(f"{path} is not a {what}: it is not HDF5 ({_looks_like(head)})")
    version = head[base + 8] if len(head) > base + 8 else -1
    # The end-of-file address is the third address field: after the base address and the
    # superblock extension (versions 2, 3) or the free-space address (versions 0, 1).
    if version in (2, 3):
        offsets_size, flags_at, addresses_at = head[base + 9 : base + 10], base + 11, base + 12
    elif version in (0, 1):
        offsets_size, flags_at = head[base + 13 : base + 14], base + 20
        addresses_at = base + (24 if version == 0 else 28)
    else:
        raise ValueError(f"{path}: superblock version {version} is unknown, or the file is cut short")
    size = offsets_size[0] if offsets_size else 0
    end_at = addresses_at + 2 * size
    if size not in (2, 4, 8) or len(head) < end_at + size:
        raise ValueError(f"{path} is cut short or damaged: its HDF5 superblock is incomplete")
    flags = head[flags_at] if version >= 2 else int.from_bytes(head[flags_at : flags_at + 4], "little")
    return Superblock(version, flags, base + int.from_bytes(head[end_at : end_at + size], "little"))


@contextlib.contextmanager
def open_checked(path: str | os.PathLike, mode: str = "r", *, what: str = "HDF5 file") -> Iterator[h5py.File]:
    """Open an HDF5 file for reading or appending, refusing damage promptly.

    A context manager. Before HDF5 sees the file its superblock is read: a truncated file is
    refused at once (a file a recorder holds open for SWMR writing gets `GROWTH_WAIT`
    seconds to reach its recorded end). A file a recorder is writing, or was writing when it
    was killed, reads through SWMR access. The discipline is in the docstring of this module
    and of `diffeit.io`.

    Arguments:
        path: The HDF5 file.
        mode: "r" to read, "r+" to append.
        what: What the file is, for the error messages ("diffeit frames file").

    Returns:
        The open `h5py.File`, closed when the `with` block ends.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file, for one that is empty, not HDF5, truncated, damaged, or
            (for "r+") marked open for writing; and for errors HDF5 raises inside the `with`
            block (a failed checksum).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such {what}: {path}")
    superblock = _complete_superblock(path, what)
    if mode == "r+" and superblock.open_for_writing:
        raise ValueError(
            f"{path} is marked open for writing: a recorder is still writing it, or was killed before it closed "
            "the file. Its frames read as they are; to append, first clear the mark with "
            f"`h5clear -s {path}` (Debian package hdf5-tools)"
        )
    # A writer that did not close the file left it marked open; SWMR access reads it regardless.
    swmr = mode == "r" and superblock.open_for_writing and superblock.version >= 3
    # Built outside the `try`: an HDF5 without the setting is not damage in the file.
    access = _swmr_access() if swmr else None
    try:
        file = _open_locked(path, mode, access)
    except (OSError, RuntimeError, ValueError) as error:
        raise ValueError(f"{path} is damaged or not a {what}: {_first_line(error)}") from None
    with file:
        try:
            yield file
        except (OSError, RuntimeError, KeyError, TypeError) as error:
            failure = _ReadDuringWrite if swmr else ValueError
            raise failure(f"{path} is damaged: {_first_line(error)}") from None


def read_checked(
    path: str | os.PathLike, read: Callable[[h5py.File], Any], *, what: str = "HDF5 file", warn_unchecked: bool = True
) -> Any:
    """Read an HDF5 file with `read(file)`, opened by `open_checked`.

    A file a writer holds open may be caught mid-write (a chunk half rewritten fails its
    checksum): its reading is tried again for up to `REREAD_WAIT` seconds before the failure
    is reported.

    Arguments:
        path: The HDF5 file.
        read: Reads what is wanted from the open file.
        what: What the file is, for the error messages.
        warn_unchecked: Warn when the file's datasets carry no checksums.

    Returns:
        What `read` returns.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: As `open_checked`.

    Warns:
        diffeit.io.NoChecksumWarning: With `warn_unchecked`, when datasets of the file carry
            no checksums.
    """
    path = Path(path)
    deadline = time.monotonic() + REREAD_WAIT
    while True:
        try:
            with open_checked(path, "r", what=what) as file:
                value = read(file)
                if warn_unchecked:
                    _warn_if_unchecked(file, path)
                return value
        except _ReadDuringWrite as error:
            if time.monotonic() > deadline:
                raise ValueError(str(error)) from None
            time.sleep(0.02)


def create_checked(group: h5py.Group, name: str, data: ArrayLike, **options: Any) -> h5py.Dataset:
    """Create a checksummed dataset holding `data`.

    An array gets HDF5's Fletcher-32 checksum (chunked); a scalar sits in compact layout,
    where the object header's checksum covers it.

    Arguments:
        group: The HDF5 group (or file) to create the dataset in.
        name: The dataset's name.
        data: Its values.
        **options: Passed on to `h5py.Group.create_dataset` for an array (such as `maxshape`
            and `chunks`).

    Returns:
        The new `h5py.Dataset`.

    Raises:
        ValueError: For a scalar given `options`.
    """
    values = np.asarray(data)
    if values.ndim == 0:
        if options:
            raise ValueError(f"{name}: a scalar dataset takes no options; got {sorted(options)}")
        creation = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        creation.set_layout(h5py.h5d.COMPACT)
        identifier = h5py.h5d.create(
            group.id,
            name.encode(),
            h5py.h5t.py_create(values.dtype, logical=True),
            h5py.h5s.create(h5py.h5s.SCALAR),
            dcpl=creation,
        )
        identifier.write(h5py.h5s.ALL, h5py.h5s.ALL, np.ascontiguousarray(values))
        return group[name]
    if values.size == 0 and "chunks" not in options:
        options = {"chunks": True, "maxshape": (None, *values.shape[1:]), **options}
    return group.create_dataset(name, data=values, fletcher32=True, **options)


def write_attributes(item: h5py.Group | h5py.Dataset, attributes: dict[str, Any]) -> None:
    """Set attributes of an HDF5 group or dataset, each stored in its object header, whose
    checksum covers it.

    A string (or a list of strings) is stored as fixed-length UTF-8: h5py would otherwise put
    it in HDF5's global heap, whose bytes no checksum covers, and an altered byte there would
    read as another string. `read_attributes` reads them back as `str`.

    Arguments:
        item: The group (or file) or dataset.
        attributes: Name -> value: a string, a list of strings, or what h5py stores as it is
            (numbers, arrays of numbers).
    """
    for name, value in attributes.items():
        item.attrs.create(name, _inline(value))


def read_attributes(item: h5py.Group | h5py.Dataset) -> dict[str, Any]:
    """The attributes of an HDF5 group or dataset, strings (fixed-length or, in files written
    before `write_attributes`, variable-length) as `str` and lists of strings as lists of `str`."""
    return {name: _text(value) for name, value in item.attrs.items()}


def _inline(value: Any) -> Any:
    if isinstance(value, str):
        encoded = value.encode("utf-8")
        return np.array(encoded, dtype=h5py.string_dtype("utf-8", max(len(encoded), 1)))
    if isinstance(value, list | tuple) and value and all(isinstance(item, str) for item in value):
        encoded = [item.encode("utf-8") for item in value]
        return np.array(encoded, dtype=h5py.string_dtype("utf-8", max(max(map(len, encoded)), 1)))
    return value


def _text(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.dtype.kind in "SO":
        return [item.decode("utf-8") if isinstance(item, bytes) else str(item) for item in value.tolist()]
    return value


def unchecked_datasets(file: h5py.File) -> list[str]:
    """Names of the datasets in `file` that carry no checksum (neither Fletcher-32 nor a compact
    layout under a checksummed object header)."""
    names: list[str] = []
    header_checksums = read_superblock(Path(file.filename)).version >= 2

    def visit(name: str, item: Any) -> None:
        if not isinstance(item, h5py.Dataset) or item.fletcher32:
            return
        compact = item.id.get_create_plist().get_layout() == h5py.h5d.COMPACT
        if not (compact and header_checksums):
            names.append(name)

    file.visititems(visit)
    return names


def _warn_if_unchecked(file: h5py.File, path: Path) -> None:
    """A `NoChecksumWarning` when datasets of `file` carry no checksum."""
    unchecked = unchecked_datasets(file)
    if unchecked:
        shown = ", ".join(unchecked[:4]) + (", ..." if len(unchecked) > 4 else "")
        warnings.warn(
            f"{path} carries no checksums ({shown}): it was written before diffeit stored them, and altered bytes "
            "in it cannot be detected",
            NoChecksumWarning,
            stacklevel=4,
        )


def write_atomically(path: str | os.PathLike, write: Callable[[h5py.File], None], *, overwrite: bool = False) -> Path:
    """Create an HDF5 file by `write(file)` under a temporary name, then rename it into place.

    An interrupted write leaves no half-written file at `path` (and, with `overwrite=True`,
    the old file intact). The file is written in the HDF5 1.10 format and flushed to disk
    (fsync) before it is renamed; without `overwrite`, a file that appears at `path`
    meanwhile is never replaced.

    Arguments:
        path: The file to create.
        write: Writes the contents into the open file (use `create_checked` for datasets).
        overwrite: Replace an existing file at `path`.

    Returns:
        `path`, as a `Path`.

    Raises:
        FileExistsError: For an existing `path` without `overwrite`.
        FileNotFoundError: When the folder of `path` does not exist.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"the folder of {path} does not exist")
    # Not tempfile.mkstemp: its files are private (mode 0600); h5py creates with the umask's mode.
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.partial")
    try:
        with h5py.File(temporary, "x", libver=LIBVER) as file:
            write(file)
        # On disk before it takes the name: a power cut then leaves the old file or the new one.
        with open(temporary, "rb") as written:
            os.fsync(written.fileno())
        _publish(temporary, path, overwrite)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
    return path


def _complete_superblock(path: Path, what: str) -> Superblock:
    """The superblock of a file that reaches its recorded end; a file a SWMR writer holds gets
    `GROWTH_WAIT` seconds to get there (its writer may be extending it right now)."""
    deadline = time.monotonic() + GROWTH_WAIT
    while True:
        superblock = read_superblock(path, what)
        size = path.stat().st_size
        if size >= superblock.end:
            return superblock
        if not superblock.swmr_writing or time.monotonic() > deadline:
            raise ValueError(
                f"{path} is truncated: it holds {size} bytes of the {superblock.end} its HDF5 superblock records "
                "(an interrupted copy or download, or a full disk?)"
            )
        time.sleep(0.02)


def _open_locked(path: Path, mode: str, swmr_access: h5py.h5p.PropFAID | None) -> h5py.File:
    """h5py.File, waiting up to LOCK_WAIT seconds while another process holds the file's lock
    (a recorder creating the file, or reopening it as it closes); read with SWMR access through
    `swmr_access` when given."""
    deadline = time.monotonic() + LOCK_WAIT
    while True:
        try:
            if swmr_access is None:
                return h5py.File(path, mode)
            flags = h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ
            return h5py.File(h5py.h5f.open(os.fsencode(path), flags, fapl=swmr_access))
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def _swmr_access() -> h5py.h5p.PropFAID:
    """File access for SWMR reading: SWMR_READ_ATTEMPTS tries of a metadata block, set by
    H5Pset_metadata_read_attempts, which h5py does not wrap (called through ctypes in the HDF5
    library h5py is linked to)."""
    access = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    setter = _hdf5_function("H5Pset_metadata_read_attempts")
    setter.argtypes, setter.restype = [ctypes.c_int64, ctypes.c_uint], ctypes.c_int
    if setter(access.id, SWMR_READ_ATTEMPTS) < 0:
        raise RuntimeError(f"HDF5 refused {SWMR_READ_ATTEMPTS} metadata read attempts")
    return access


@functools.cache
def _hdf5_function(name: str) -> Any:
    """A function of the HDF5 library that h5py uses. Looked up through h5py's own extension
    module, whose symbol scope holds the library it was linked to (Linux, macOS), then in the
    libraries h5py's wheels bundle beside it (Windows)."""
    folder = Path(h5py.__file__).parent
    candidates = [Path(h5py.h5p.__file__)]
    for bundle in (folder, folder.parent / "h5py.libs", folder / ".dylibs"):
        candidates += sorted(p for p in bundle.glob("*hdf5*") if "_hl" not in p.name and p.suffix != ".py")
    for candidate in candidates:
        with contextlib.suppress(OSError, AttributeError):
            return getattr(ctypes.CDLL(str(candidate)), name)
    raise RuntimeError(
        f"{name} was not found in the HDF5 library h5py uses; diffeit cannot read a file a recorder holds open "
        "without risking a hang on damage"
    )


def _publish(temporary: Path, path: Path, overwrite: bool) -> None:
    """Move the finished file into place; without `overwrite`, never replace a file that
    appeared meanwhile (a hard link fails when the name exists)."""
    if overwrite:
        os.replace(temporary, path)
        return
    try:
        os.link(temporary, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it") from None
    except OSError:  # file systems without hard links
        if path.exists():
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it") from None
        os.replace(temporary, path)


def _looks_like(head: bytes) -> str:
    """A guess at what a file that is not HDF5 is, for the error message."""
    kinds = {
        b"\x89PNG": "a PNG image",
        b"PK\x03\x04": "a zip archive, such as a NumPy .npz",
        b"MATLAB": "a MATLAB .mat file",
        b"%PDF": "a PDF document",
    }
    for magic, kind in kinds.items():
        if head.startswith(magic):
            return kind
    if head.startswith(_SIGNATURE[:4]):
        return "its signature is damaged"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return "no HDF5 signature"
    return "a text file"


def _first_line(error: BaseException) -> str:
    text = str(error.args[0] if isinstance(error, KeyError) and error.args else error).strip()
    return text.splitlines()[0] if text else type(error).__name__
