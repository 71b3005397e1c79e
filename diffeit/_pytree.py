"""Frozen dataclasses as JAX pytrees."""

from dataclasses import fields

import jax


def register_dataclass(cls: type, static: tuple[str, ...] = ()) -> type:
    """Register the frozen dataclass `cls` as a JAX pytree: the fields named in `static` are
    auxiliary data (hashable settings), the others leaves. Unflattening skips `__post_init__`:
    transformations rebuild objects from tracers or placeholders, which cannot be checked."""
    names = tuple(f.name for f in fields(cls))
    leaves = tuple(name for name in names if name not in static)

    def flatten_with_keys(obj):
        children = tuple((jax.tree_util.GetAttrKey(name), getattr(obj, name)) for name in leaves)
        return children, tuple(getattr(obj, name) for name in static)

    def flatten(obj):
        return tuple(getattr(obj, name) for name in leaves), tuple(getattr(obj, name) for name in static)

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for name, value in zip(leaves + static, tuple(children) + tuple(aux), strict=True):
            object.__setattr__(obj, name, value)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
    return cls
