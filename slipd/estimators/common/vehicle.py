"""Checks of the vehicle vector a method needs, at load time (``init``), never in a kernel."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from slipd.channels import N_VEH, Veh
from slipd.errors import ConfigError


def require_vehicle(method: str, vehicle: np.ndarray, positive: Iterable[Veh],
                    finite: Iterable[Veh] = ()) -> None:
    """Refuse a vehicle vector ``method`` cannot use: the wrong shape, a ``positive`` element
    that is not finite and > 0, a ``finite`` one that is not finite (names the element and the
    profile table it comes from)."""
    if vehicle.shape != (N_VEH,):
        raise ConfigError(f"{method}: vehicle vector has shape {vehicle.shape}, "
                          f"expected ({N_VEH},)")
    for field in positive:
        value = float(vehicle[field])
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"{method}: vehicle {field.name.lower()} = {value}: must be "
                              "finite and > 0 (profile [vehicle] table)")
    for field in finite:
        value = float(vehicle[field])
        if not math.isfinite(value):
            raise ConfigError(f"{method}: vehicle {field.name.lower()} = {value}: must be "
                              "finite (profile [vehicle] table)")
