"""Array helpers shared by the modules of diffeit."""

import dataclasses
import hashlib

import equinox as eqx
import jax
import jax.numpy as jnp
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


def rms(values: np.ndarray) -> float:
    """The root mean square of `values`."""
    return float(np.sqrt(np.mean(np.square(values))))


# A reading under this fraction of its readings' RMS has an uncertain sign: noise or the
# model's error can flip it, and a ratio to it blows up.
UNCERTAIN_SIGN = 0.05


def uncertain_sign(readings: np.ndarray) -> np.ndarray:
    """(M,) bool, the `readings` (M,) under `UNCERTAIN_SIGN` of their RMS."""
    return np.abs(readings) < UNCERTAIN_SIGN * rms(readings)


def per_element(background: float | np.ndarray, n_elements: int) -> jax.Array:
    """(E,) a background conductivity given as one level or per element (a calibration's
    `background`), as a float array of one value per element."""
    return jnp.broadcast_to(jnp.asarray(background, float), (n_elements,))


class StaticData:
    """Immutable data that JAX treats as static (a pytree without leaves), compared and hashed
    by content: meshes, protocols, sparsity patterns, assembled electrode systems. Two equal
    meshes built separately key the same compiled functions, so a second model on an equal
    mesh compiles nothing.

    A subclass is a `dataclass(eq=False)` with its own `__init__`, which validates its input
    and assigns every field once, `fingerprint` (bytes, see `fingerprint`) included. A field
    cannot be assigned again or deleted: the data is fixed at construction. Models hold such
    data in static fields (`eqx.field(static=True)`); everything with array leaves is an
    `equinox.Module`.
    """

    fingerprint: bytes

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        jax.tree_util.register_static(cls)

    def __setattr__(self, name: str, value) -> None:
        if name in self.__dict__:
            raise dataclasses.FrozenInstanceError(f"cannot assign to {name!r}: {type(self).__name__} is immutable")
        super().__setattr__(name, value)

    def __delattr__(self, name: str) -> None:
        raise dataclasses.FrozenInstanceError(f"cannot delete field {name!r}: {type(self).__name__} is immutable")

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.fingerprint == other.fingerprint

    def __hash__(self) -> int:
        return hash((type(self).__qualname__, self.fingerprint))


class IdentityModule(eqx.Module):
    """An `equinox.Module` compared and hashed by identity, as functions are: `jax.jit(model.measure)`
    hashes the bound method, and with it the object, whose array fields have no hash. Models
    and reconstructions subclass it."""

    def __eq__(self, other: object) -> bool:
        return self is other

    def __hash__(self) -> int:
        return id(self)


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only copy of `array`: meshes and protocols never change after construction."""
    array = np.array(array)
    array.setflags(write=False)
    return array


def frame_period(times: np.ndarray) -> float:
    """The frames' median period, s, from their `times` (T,); 0 for fewer than two frames."""
    return float(np.median(np.diff(times))) if len(times) >= 2 else 0.0


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
