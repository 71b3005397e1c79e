"""Array helpers shared by the modules of diffeit."""

import hashlib

import jax
import numpy as np


def fingerprint(*parts: np.ndarray | bytes) -> bytes:
    """A 16-byte digest of arrays (their dtypes, shapes and values) and byte strings, in order:
    equal content gives equal fingerprints."""
    digest = hashlib.blake2b(digest_size=16)
    for part in parts:
        if isinstance(part, bytes):
            digest.update(part)
            continue
        array = np.ascontiguousarray(part)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.digest()


class ContentIdentity:
    """Equality and hashing by content, for the immutable static data JAX sees (meshes,
    protocols, sparsity patterns, assembled systems): two equal meshes built separately key
    the same compiled functions, so a second model on an equal mesh compiles nothing. A
    subclass sets `fingerprint` (bytes, see `fingerprint`) at construction."""

    fingerprint: bytes

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.fingerprint == other.fingerprint

    def __hash__(self) -> int:
        return hash((type(self).__qualname__, self.fingerprint))


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`: meshes and protocols never change after construction."""
    array = np.array(array)
    array.setflags(write=False)
    return array


def is_concrete(x) -> bool:
    """Whether `x` holds values (not a tracer under jit, vmap or grad): values are checked
    with messages naming the offenders only then."""
    return not isinstance(x, jax.core.Tracer)


def concrete_floats(value, name: str) -> np.ndarray | None:
    """`value` as a float array, or None when any part of it is traced (checked at run time
    instead); a ValueError naming `name` when it is not numbers or not finite."""
    if not all(is_concrete(leaf) for leaf in jax.tree_util.tree_leaves(value)):
        return None
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers; got {value!r}") from None
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite; got {array}")
    return array
