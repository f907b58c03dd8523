"""The estimators: one shape for every method, registered by name (``registry``).

A method is a module (``zero.py``, ``linear_kf.py``, or a package: ``ensemble/`` and one per
paper: ``selmanaj2017/``, ``righetti_lenzo2025/``, ``carnier2023/``, ``chen2018/``,
``yoon2016/``) built from the blocks in ``common/`` (layouts, inputs, filters, kinematics,
tyres, Kalman algebra, outputs, vehicle checks). It exposes:

``PARAMS``
    an ``enum.IntEnum`` naming the elements of its float64 params vector;
``DEFAULTS``
    ``{field_name: value}`` with the paper's published values (the docstring cites the table);
``LAYOUT``
    its state layout (``common.layout.build_layout``): named slots, size, hash;
``init(params, vehicle) -> np.ndarray``
    the float64 state vector at start (or at reset), ``LAYOUT.size`` long; it refuses a vehicle
    or params the kernels cannot use (``ConfigError`` naming the element);
``step(state, u, params, vehicle, dt, out)``
    ``@numba.njit(cache=True)``; reads the per-tick input ``u`` (see ``slipd.channels``: values,
    validity flags at ``VALID + ch``, tick time at ``U_TIME``), advances ``state`` in place and
    writes every element of ``out`` (``slipd.channels.Out``). It allocates nothing;
``run_ticks(state, U, params, vehicle, dt, OUT)``
    ``@numba.njit(cache=True)``; the batch loop ``for k: step(state, U[k], ..., OUT[k])``.
    It lives beside ``step`` because numba cannot cache a kernel that takes another jitted
    function as an argument or closes over one (measured: it recompiles in every process);
``REQUIRED`` (optional)
    the channels whose loss makes its output invalid (default ``channels.CORE_CHANNELS``);
``PERSISTENT`` (optional)
    names of state elements the daemon keeps across restarts (learnt offsets, calibrations).

A method writes ``Status.NOT_CONVERGED`` until it has settled, ``Status.UNAVAILABLE`` when a
sensor it needs is absent (it never invents the data), ``Status.RESET`` on the tick it resets
itself. ``slipd.pipeline`` adds the input-supervision bits and decides VALID
(``supervision``), the same in the daemon and in replay.

Adding a method: write its module (or package), add one ``Spec`` line to
``registry.BUILTIN`` with a new, never used ``wire_id`` and its value in slipd.dbc's
ESTIMATOR_ID VAL_ table, and regenerate the golden values (tests/test_golden.py). A variant of
an existing method is a registry line with ``overrides``, not a module. A third-party package
registers through the ``slipd.estimators`` entry-point group (``registry``).
"""

from slipd.estimators.registry import Method, Spec, available, load, make_params, spec

__all__ = ["Method", "Spec", "available", "load", "make_params", "spec"]
