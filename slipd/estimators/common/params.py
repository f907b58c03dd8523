"""A method's params vector: each parameter named once, with its default.

``build_params`` turns ``(NAME, default)`` pairs into the ``PARAMS`` IntEnum the kernels index
the float64 params vector with, and the ``DEFAULTS`` dict (lower-case names) that
``registry.make_params`` fills it from. A family of methods shares the pairs it has in common
instead of repeating them.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping


def build_params(name: str, *fields: tuple[str, float]) -> tuple[type[enum.IntEnum], dict]:
    """(PARAMS, DEFAULTS) of ``fields``, numbered in the order given."""
    names = [field for field, _ in fields]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"{name}: parameter(s) {duplicated} given twice")
    params = enum.IntEnum(f"{name}_params", [(field, k) for k, field in enumerate(names)])
    return params, {field.lower(): float(value) for field, value in fields}


def nested_fields(prefix: str, params: type[enum.IntEnum],
                  values: Mapping[str, float]) -> tuple[tuple[str, float], ...]:
    """``(PREFIX__FIELD, value)`` pairs of another params vector, for a method that runs another
    method's kernel inside its own (d_ekf's friction estimator, the ensemble's members and
    their monitors): ``params`` that vector's IntEnum, ``values`` its values by lower-case
    name (a ``DEFAULTS`` dict)."""
    return tuple((f"{prefix.upper()}__{field.name}", float(values[field.name.lower()]))
                 for field in params)
