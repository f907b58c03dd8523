"""The ensemble's members (the registry's ``ensemble=True`` Specs) and its state layout: the
fusion block, then each member's own state (``ensemble`` module docstring)."""

from __future__ import annotations

import importlib
from types import ModuleType

from slipd.channels import N_IN, N_OUT, ST_INPUT_TIMEOUT, ST_NOT_CONVERGED, ST_RESET, ST_UNAVAILABLE
from slipd.estimators import consistency, registry
from slipd.estimators.common.layout import build_layout
from slipd.numba_cache import nb

#: The member methods, in the order of their slots (and of the calls in ``run_members``).
MEMBERS = (
    "kinematic_heuristic",
    "dk_ekf",
    "d_ekf",
    "k_kf",
    "hybrid_friction",
    "pseudo_fusion",
    "gnss_magnetometer",
)
_REGISTERED = tuple(spec.name for spec in registry.ensemble_members())
if _REGISTERED != MEMBERS:
    raise ImportError(f"ensemble: the registry's members {_REGISTERED} differ from the ones "
                      f"run_members calls {MEMBERS}; add the call (or the registry flag)")
N_MEMBERS = len(MEMBERS)
_SPECS = tuple(registry.spec(name) for name in MEMBERS)
_FAMILIES = tuple(dict.fromkeys(spec.family for spec in _SPECS))
#: Family of each member (an index): members of one family share kernels (dk_ekf, d_ekf and
#: k_kf are built from the same righetti_lenzo2025 dynamic EKF and kinematic KF), so their
#: errors share a part the fit models as a common term C_f (module docstring).
FAMILY = tuple(_FAMILIES.index(spec.family) for spec in _SPECS)
#: A member's status bits that take it out of the fusion this tick.
EXCLUDING = ST_UNAVAILABLE | ST_INPUT_TIMEOUT | ST_NOT_CONVERGED | ST_RESET
#: The member whose raw output is the dynamic witness of the others' consistency monitors
#: (off by default: ``member_monitor``): the d_ekf member, consistency.WITNESS's kernel with the
#: member's params (the pipeline's witness keeps the paper's friction); it has none of its own
#: inside the ensemble.
WITNESS_MEMBER = next(m for m, spec in enumerate(_SPECS)
                      if spec.module == registry.spec(consistency.WITNESS).module)
#: The members left in the fusion on a low-grip road (``low_grip_members``; module docstring):
#: the two that estimate the road's friction (d_ekf from the wheels' slip, hybrid_friction's
#: adaptive law and classifier) and the one whose beta needs no tyre model (the GNSS velocity).
LOW_GRIP_MEMBERS = ("d_ekf", "hybrid_friction", "gnss_magnetometer")
#: 1.0 for each of them, in member order (the kernel's mask)
LOW_GRIP_MASK = tuple(1.0 if name in LOW_GRIP_MEMBERS else 0.0 for name in MEMBERS)
#: The member whose friction class says the road is low-grip: d_ekf, which reports
#: hybrid_friction's slip-based classifier while that is settled (its ``slip_friction``)
FRICTION_MEMBER = MEMBERS.index("d_ekf")
#: Slots of one member's consistency monitor.
MONITOR_SIZE = consistency.LAYOUT.size




def member_module(name: str) -> ModuleType:
    return importlib.import_module(registry.spec(name).module)


#: The fusion block, then each member's state (module docstring).
LAYOUT = build_layout(
    "ensemble",
    ("STATE_BOUNDS", N_MEMBERS + 1),  # start of member m's state; [N] the end of the last
    ("PARAMS_BOUNDS", N_MEMBERS + 1),  # the same for the params vector
    ("USABLE", N_MEMBERS),  # 1.0 when the member is usable this tick
    ("USABLE_TICKS", N_MEMBERS),  # consecutive usable ticks
    ("FUSED", N_MEMBERS),  # 1.0 when the member enters this tick's fusion
    ("WEIGHT", N_MEMBERS),  # the weights w_i of the last tick
    ("VARIANCE", N_MEMBERS),  # P_ii of the last tick, rad^2 (NaN: not fused)
    ("MOMENT", N_MEMBERS * N_MEMBERS),  # D_ij (row-major, symmetric, diagonal unused)
    ("MASS", N_MEMBERS * N_MEMBERS),  # M_ij, the EWMA weight collected
    ("REQUIRED", N_MEMBERS * N_IN),  # 1.0 where member m requires channel
    ("MEMBER_OUT", N_MEMBERS * N_OUT),  # the members' outputs of this tick
    ("INDEX", N_MEMBERS),  # scratch, member of each packed index
    ("UNKNOWN", N_MEMBERS),  # scratch, unknown index of family f's C_f (-1: none)
    ("SYSTEM", 4 * N_MEMBERS * N_MEMBERS),  # scratch, normal equations, then P (2N x 2N)
    ("RHS", 2 * N_MEMBERS),  # scratch, right-hand side, then the solution
    ("SCALE", 2 * N_MEMBERS),  # scratch, the diagonal scaling
    ("COMMON", N_MEMBERS),  # C_f of family f of the last tick, rad^2
    ("MONITOR", N_MEMBERS * MONITOR_SIZE),  # each member's consistency monitor
    ("MONITOR_OUT", N_OUT),  # scratch, a member's outputs as its monitor sees them
    ("CONSISTENT", N_MEMBERS),  # 1.0 unless the member's monitor failed it this tick
    ("CALIBRATED_SIGMA", N_MEMBERS),  # rad, its monitor's calibrated sigma (NaN: not run)
    ("LOW_GRIP", 1),  # 1.0 while the road is taken as low-grip (``low_grip_members``)
    ("LOW_GRIP_CHANGE_TICKS", 1),  # consecutive ticks the friction class has said otherwise
    *((name.upper(), member_module(name).LAYOUT) for name in MEMBERS),
)
F = LAYOUT.S
FUSION_END = int(F[MEMBERS[0].upper()])  # the first member's state starts here
#: The members' persistent state (their learnt offsets and calibrations), by element name.
PERSISTENT = tuple(
    f"{name.upper()}.{member_module(name).LAYOUT.element_names[i]}" for name in MEMBERS
    for i in member_module(name).LAYOUT.indices(getattr(member_module(name), "PERSISTENT", ()))
)



@nb.njit(cache=True, inline="always")
def _member_state(state, m):
    return state[int(state[F.STATE_BOUNDS + m]) : int(state[F.STATE_BOUNDS + m + 1])]


@nb.njit(cache=True, inline="always")
def _member_params(state, params, m):
    return params[int(state[F.PARAMS_BOUNDS + m]) : int(state[F.PARAMS_BOUNDS + m + 1])]


@nb.njit(cache=True, inline="always")
def _member_monitor(state, m):
    start = F.MONITOR + m * MONITOR_SIZE
    return state[start : start + MONITOR_SIZE]


@nb.njit(cache=True, inline="always")
def _member_out(state, m):
    start = F.MEMBER_OUT + m * N_OUT
    return state[start : start + N_OUT]

