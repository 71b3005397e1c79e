"""Every reader refuses a damaged file promptly, and never returns other numbers.

Sound files of each kind are written by the project itself (tests/damaged_kinds.py); hypothesis
truncates them at any byte or flips bytes anywhere, and a worker process
(tests/damaged_worker.py) reads each damaged file. The reader must return what it returns for
the sound file, or raise a `ValueError` naming the file, within `PROMPT` seconds.
A reader that hangs fails the test when the worker does not answer within `HANG`. Formats
without checksums can only be held to the error and the time (`damaged_kinds.DAMAGE_READS_AS`).
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
from pathlib import Path
from typing import Any

import damaged_kinds
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

# What the issue asks of every reader, on this machine (seconds).
PROMPT = 2.0
# The worker is declared hung after this long (a cold start imports JAX first).
HANG = 30.0
KINDS = damaged_kinds.KINDS


class Worker:
    """The reader subprocess: `ask(kind, path)` is its answer, or a failed test when it hangs."""

    def __init__(self) -> None:
        environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
        self.process = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("damaged_worker.py"))],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=environment,
        )

    def ask(self, kind: str, path: Path) -> dict[str, Any]:
        self.process.stdin.write(json.dumps({"kind": kind, "path": str(path)}) + "\n")
        self.process.stdin.flush()
        ready, _, _ = select.select([self.process.stdout], [], [], HANG)
        if not ready:
            self.process.kill()
            pytest.fail(f"reading the damaged {kind} file {path} hung (no answer within {HANG:g} s)")
        line = self.process.stdout.readline()
        if not line:
            pytest.fail(f"the reader process died reading the damaged {kind} file {path}")
        return json.loads(line)

    def close(self) -> None:
        self.process.kill()
        self.process.wait()


@pytest.fixture(scope="module")
def worker():
    reader = Worker()
    yield reader
    reader.close()


@pytest.fixture(scope="module")
def sound(tmp_path_factory, worker) -> dict[str, tuple[Path, dict[str, Any]]]:
    """Each kind's sound file and what its reader answers for it."""
    folder = tmp_path_factory.mktemp("sound")
    files = {}
    for kind in KINDS:
        path = damaged_kinds.WRITERS[kind](folder)
        answer = worker.ask(kind, path)
        assert answer["outcome"] == "data", (kind, answer)
        files[kind] = (path, answer)
    return files


# A damage: cut the file at a fraction of its length, or xor bytes at fractions of its length.
DAMAGE = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0, exclude_max=True)),
    st.tuples(
        st.just("flip"),
        st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=8),
    ),
)


def damaged(content: bytes, damage: tuple) -> bytes:
    how, where = damage
    if how == "truncate":
        return content[: int(where * len(content))]
    altered = bytearray(content)
    for fraction, mask in where:
        altered[int(fraction * len(content))] ^= mask
    return bytes(altered)


@pytest.mark.parametrize("kind", KINDS)
@settings(
    max_examples=25,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(damage=DAMAGE)
# A metadata byte of the recorder's file, which HDF5's SWMR reader retried for hours.
@example(damage=("flip", [(0.013, 145)]))
def test_a_damaged_file_is_refused_promptly_or_read_as_written(kind, damage, sound, worker, tmp_path):
    """What a damaged file may read as depends on its format (`damaged_kinds.DAMAGE_READS_AS`):
    the sound file's data ("whole"), some of its frames, each as sent ("frames"), or, in
    formats without checksums, what the bytes now say ("as written": only the error and the time
    are checked)."""
    original, expected = sound[kind]
    path = tmp_path / f"damaged-{original.name}"
    path.write_bytes(damaged(original.read_bytes(), damage))
    answer = worker.ask(kind, path)
    assert answer["seconds"] < PROMPT, (kind, damage, answer)
    if answer["outcome"] == "error":
        assert answer["type"] == "ValueError", (kind, damage, answer)
        assert path.name in answer["message"], (kind, damage, answer)
        return
    reads_as = damaged_kinds.DAMAGE_READS_AS[kind]
    if reads_as == "whole":
        assert answer["digests"] == expected["digests"], f"{kind}: {damage} read as other numbers"
    elif reads_as == "frames":
        other = {key for key, value in answer["digests"].items() if expected["digests"].get(key) != value}
        assert not other, f"{kind}: {damage} read frames {sorted(other)} as other numbers"


@pytest.mark.parametrize("kind", [kind for kind in KINDS if damaged_kinds.DAMAGE_READS_AS[kind] != "frames"])
def test_an_empty_file_and_a_file_of_another_kind_are_refused(kind, sound, worker, tmp_path):
    """(A stream has no file to refuse: its parser counts what it cannot read as drops.)"""
    suffix = sound[kind][0].suffix
    empty = tmp_path / f"empty{suffix}"
    empty.write_bytes(b"")
    other_kind = next(other for other in KINDS if sound[other][0].suffix != suffix)
    other = tmp_path / f"other{suffix}"
    other.write_bytes(sound[other_kind][0].read_bytes())
    noise = tmp_path / f"noise{suffix}"
    noise.write_bytes(np.random.default_rng(7).bytes(4096))
    for path in (empty, other, noise):
        answer = worker.ask(kind, path)
        assert answer["outcome"] == "error" and answer["type"] == "ValueError", (kind, path.name, answer)
        assert path.name in answer["message"] and answer["seconds"] < PROMPT, (kind, path.name, answer)


HDF5_KINDS = [kind for kind in KINDS if kind in ("frames", "recorder", "fit", "skin_calibration")]


@pytest.mark.parametrize("kind", HDF5_KINDS)
def test_every_string_attribute_is_checksummed(kind, sound, worker, tmp_path):
    """HDF5 keeps a variable-length string in its global heap, which no checksum covers: every
    string attribute of diffeit's files is fixed-length, in an object header. A byte altered
    inside one (the middle of the longest) is refused."""
    import h5py

    original, _ = sound[kind]
    longest = b""
    with h5py.File(original, "r", swmr=kind == "recorder") as file:

        def visit(name, item):
            nonlocal longest
            for key, value in item.attrs.items():
                # h5py reads a variable-length string as str, a fixed-length one as bytes.
                assert not isinstance(value, str), f"{kind}: attribute {key!r} of {name!r} is a variable-length string"
                if isinstance(value, bytes) and len(value) > len(longest):
                    longest = bytes(value)

        visit("/", file)
        file.visititems(visit)
    content = bytearray(original.read_bytes())
    where = content.find(longest)
    assert len(longest) > 3 and where > 0, kind
    content[where + len(longest) // 2] ^= 0x55
    path = tmp_path / f"altered-{original.name}"
    path.write_bytes(bytes(content))
    answer = worker.ask(kind, path)
    assert answer["outcome"] == "error" and answer["type"] == "ValueError", (kind, answer)
    assert path.name in answer["message"] and answer["seconds"] < PROMPT, (kind, answer)
