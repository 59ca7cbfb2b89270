"""PyTree registration that keeps classes apart.

``jax.tree_util.register_dataclass`` (jax 0.10.2) gives two classes with the same field names
tree structures that compare *equal* (the type is not part of a dataclass node's equality,
only its fields), although their hashes differ. Code that matches structures by equality
can then hand one class's leaves to a program built for the other: once, in a full test
run, the autodiff Jacobian of Rot3 between factors came out shaped like a Pose2 between
Jacobian evaluated on the quaternions (read as cos, sin, x, y). jaxslam's families of
same-field classes (Lie groups, variable types, robust kernels, factors) are registered here
instead, with the class in the structure's auxiliary data.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax


def register_typed(cls: type, data_fields: Sequence[str]) -> None:
    """Register ``cls`` as a PyTree whose leaves are ``data_fields`` (rebuilt by keyword) and
    whose structure names the class, so different classes never compare equal."""
    fields = tuple(data_fields)
    tag = f"{cls.__module__}.{cls.__qualname__}"

    keys = tuple(jax.tree_util.GetAttrKey(f) for f in fields)

    def flatten_with_keys(obj: Any) -> tuple[tuple[tuple[Any, Any], ...], str]:
        return tuple((k, getattr(obj, f)) for k, f in zip(keys, fields)), tag

    def flatten(obj: Any) -> tuple[tuple[Any, ...], str]:
        return tuple(getattr(obj, f) for f in fields), tag

    def unflatten(_: str, children: Any) -> Any:
        return cls(**dict(zip(fields, children)))

    # key paths name the fields (``.measured``), as a dataclass registration's do
    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
