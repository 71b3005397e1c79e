"""The reading half of tests/test_damaged_files.py, run in a subprocess so that a reader that
hangs on a damaged file fails the test (the parent times it out) instead of stalling the suite.

Reads requests from stdin, one JSON object a line: {"kind": ..., "path": ...}; answers on stdout,
one JSON object a line: {"outcome": "data", "digests": ...} when the reader returned (the digest
of what it returned, to compare with the sound file's: of each frame by counter for a stream,
else of the whole) or {"outcome": "error", "type": ..., "message": ...}, with "seconds" the
reader took. The readers are the `read_<kind>` functions of
tests/damaged_kinds.py.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import damaged_kinds
import numpy as np


def digest(value: Any) -> str:
    """A hash of everything `value` holds: arrays by dtype, shape and bytes; dataclasses and
    equinox Modules by their fields; mappings, sequences and scalars by their items."""
    hasher = hashlib.sha256()
    _feed(hasher, value)
    return hasher.hexdigest()


def _feed(hasher: Any, value: Any) -> None:
    if hasattr(value, "__array__") and not isinstance(value, str | bytes):
        array = np.asarray(value)
        hasher.update(f"array {array.dtype} {array.shape}".encode())
        hasher.update(np.ascontiguousarray(array).tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        hasher.update(type(value).__name__.encode())
        for field in dataclasses.fields(value):
            hasher.update(field.name.encode())
            _feed(hasher, getattr(value, field.name))
    elif isinstance(value, dict):
        for key in sorted(value, key=str):
            hasher.update(repr(key).encode())
            _feed(hasher, value[key])
    elif isinstance(value, list | tuple):
        hasher.update(f"sequence {len(value)}".encode())
        for item in value:
            _feed(hasher, item)
    else:
        hasher.update(repr(value).encode())


def answer(kind: str, path: Path) -> dict[str, Any]:
    reader = getattr(damaged_kinds, f"read_{kind}")
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            value = reader(path)
        parts = value if damaged_kinds.DAMAGE_READS_AS[kind] == "frames" else {"whole": value}
        outcome = {"outcome": "data", "digests": {str(key): digest(part) for key, part in parts.items()}}
    except Exception as error:  # every failure is reported, its type judged by the parent
        outcome = {"outcome": "error", "type": type(error).__name__, "message": str(error)}
    return {**outcome, "seconds": time.perf_counter() - start}


def main() -> None:
    for line in sys.stdin:
        request = json.loads(line)
        print(json.dumps(answer(request["kind"], Path(request["path"]))), flush=True)


if __name__ == "__main__":
    main()
