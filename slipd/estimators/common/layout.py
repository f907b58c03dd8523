"""State-vector layouts: the named slots and blocks of a method's float64 state, built once.

A method's state is one flat float64 array (numba kernels index it with plain ints). Its
layout names every element: a field is one slot, a block of ``n`` slots, or a block whose
elements an ``enum.IntEnum`` names (``("OFFSETS", Offsets)``). ``build_layout`` places the
fields one after the other, so no two names can share a slot and no hand-typed offset
(``N = LAST + 12``) can go stale; it returns the ``IntEnum`` of the fields' first slots for
the kernels (``state[S.KF_P + 2]``), each block's length, the total size and a hash of the
whole layout (names, positions, lengths), which persisted state carries so that a state
saved under another layout is never restored into the wrong slots.
"""

from __future__ import annotations

import enum
import hashlib
from collections.abc import Iterable
from dataclasses import dataclass

FieldSpec = str | tuple[str, "int | type[enum.IntEnum] | Layout"]


@dataclass(frozen=True)
class Layout:
    """A built layout. ``S`` is the IntEnum of field starts; ``size`` the state length."""

    name: str
    S: type[enum.IntEnum]
    lengths: dict[str, int]
    element_names: tuple[str, ...]
    size: int

    @property
    def hash(self) -> str:
        """12 hex digits over every element's name and position (the layout's identity)."""
        digest = hashlib.sha256(self.name.encode())
        for index, name in enumerate(self.element_names):
            digest.update(f"\n{index}:{name}".encode())
        return digest.hexdigest()[:12]

    def span(self, field: str) -> range:
        """The slots of ``field``."""
        start = int(self.S[field])
        return range(start, start + self.lengths[field])

    def indices(self, names: Iterable[str]) -> tuple[int, ...]:
        """State indices of ``names``: whole fields (``"CAL_C"``) or single elements
        (``"OFFSETS.AX"``, ``"CAL_C[3]"``), in the order given."""
        by_element = {name: i for i, name in enumerate(self.element_names)}
        result: list[int] = []
        for name in names:
            if name in self.lengths:
                result.extend(self.span(name))
            elif name in by_element:
                result.append(by_element[name])
            else:
                raise KeyError(f"{self.name}: no state field or element {name!r}")
        return tuple(result)


def build_layout(name: str, *fields: FieldSpec) -> Layout:
    """Place ``fields`` one after the other: ``"VX"`` (one slot), ``("P", 10)`` (a block of
    10, elements ``P[0]`` ..), ``("OFFSETS", Offsets)`` (a block named by an IntEnum whose
    values are 0 .. n-1, elements ``OFFSETS.YAW_RATE`` ..), ``("MEMBER", layout)`` (another
    layout nested as a block, elements ``MEMBER.<its element>``)."""
    members: list[tuple[str, int]] = []
    lengths: dict[str, int] = {}
    elements: list[str] = []
    position = 0
    for spec in fields:
        field, kind = (spec, 1) if isinstance(spec, str) else spec
        if field in lengths:
            raise ValueError(f"layout {name}: field {field} given twice")
        if isinstance(kind, Layout):
            length = kind.size
            elements += [f"{field}.{element}" for element in kind.element_names]
        elif isinstance(kind, int):
            if kind < 1:
                raise ValueError(f"layout {name}: field {field} has length {kind}")
            length = kind
            elements += [field] if length == 1 else [f"{field}[{k}]" for k in range(length)]
        else:
            values = sorted(int(member) for member in kind)
            if values != list(range(len(values))):
                raise ValueError(f"layout {name}: block {field} ({kind.__name__}) must number "
                                 "its elements 0 .. n-1")
            length = len(values)
            elements += [f"{field}.{member.name}" for member in sorted(kind, key=int)]
        members.append((field, position))
        lengths[field] = length
        position += length
    return Layout(name, enum.IntEnum(f"{name}_state", members), lengths, tuple(elements),
                  position)
