"""The contract every registered method keeps (slipd.estimators): params, state, outputs,
status bits, no allocation. One test per Spec, on the codec drives and on broken inputs."""

from __future__ import annotations

import enum

import numpy as np
import pytest
from nrt import allocations, sine_drive_inputs

from slipd.channels import N_IN, N_OUT, ST_VALID, U_LEN, VALID, In, Out, Status
from slipd.estimators import registry

DT = 0.01
SENTINEL = -123456.789
LEGAL_STATUS = sum(int(s) for s in Status)
#: the outputs every method must give finite on every tick (mu and sigma may be NaN: "not
#: estimated" / "unknown")
ALWAYS_FINITE = (Out.BETA, Out.BETA_RATE, Out.VX, Out.VY, Out.ROLL, Out.FRICTION_CLASS,
                 Out.STATUS)
NAMES = [spec.name for spec in registry.BUILTIN]


def broken_inputs(U: np.ndarray) -> np.ndarray:
    """A stretch of ``U`` with every failure at once: channels invalid, garbage behind invalid
    flags, a total outage."""
    U = U.copy()
    rng = np.random.default_rng(1)
    dropped = rng.random((len(U), N_IN)) < 0.2
    U[:, VALID : VALID + N_IN][dropped] = 0.0
    U[:, :N_IN][dropped] = np.nan
    U[len(U) // 2 : len(U) // 2 + 30, VALID : VALID + N_IN] = 0.0
    U[len(U) // 2 : len(U) // 2 + 30, :N_IN] = np.inf
    return U


@pytest.mark.parametrize("name", NAMES)
def test_params_and_state_have_the_shapes_the_contract_says(name, vehicle):
    method = registry.load(name)
    module = method.module
    assert issubclass(module.PARAMS, enum.IntEnum)
    assert sorted(int(p) for p in module.PARAMS) == list(range(len(module.PARAMS)))
    assert set(module.DEFAULTS) == {p.name.lower() for p in module.PARAMS}
    assert method.params.dtype == np.float64 and method.params.shape == (len(module.PARAMS),)
    state = method.init(vehicle)
    assert state.dtype == np.float64 and state.shape == (module.LAYOUT.size,)
    assert set(method.required) <= set(In)
    method.layout.indices(method.persistent)
    for attribute in ("step", "run_ticks"):
        assert hasattr(getattr(module, attribute), "py_func"), f"{name}.{attribute} is not jitted"


@pytest.mark.parametrize("name", NAMES)
def test_step_writes_every_output_with_legal_status_bits(name, vehicle, codec_drives):
    method = registry.load(name)
    state = method.init(vehicle)
    U = np.concatenate([drive.inputs.U[:400] for drive in codec_drives.values()])
    U = np.concatenate([U, broken_inputs(U[:300])])
    out = np.empty(N_OUT)
    for k, u in enumerate(U):
        out[:] = SENTINEL
        method.step(state, u, method.params, vehicle, DT, out)
        assert not np.any(out == SENTINEL), (name, k, [Out(i).name for i in
                                                        np.flatnonzero(out == SENTINEL)])
        assert np.all(np.isfinite(out[list(ALWAYS_FINITE)])), (name, k, out)
        status = int(out[Out.STATUS])
        assert status == out[Out.STATUS] and status & ~LEGAL_STATUS == 0, (name, k, status)
        assert not status & ST_VALID, f"{name} set VALID itself (only supervision may)"
        assert 0.0 <= out[Out.FRICTION_CLASS] <= 3.0


def test_run_ticks_is_the_loop_of_step(vehicle, codec_drives):
    U = np.ascontiguousarray(codec_drives["mu_jump"].inputs.U[:500])
    for name in NAMES:
        method = registry.load(name)
        batch = np.zeros((len(U), N_OUT))
        method.run_ticks(method.init(vehicle), U, method.params, vehicle, DT, batch)
        state = method.init(vehicle)
        stepped = np.zeros((len(U), N_OUT))
        for k in range(len(U)):
            method.step(state, U[k], method.params, vehicle, DT, stepped[k])
        np.testing.assert_array_equal(batch, stepped, err_msg=name)


def test_no_method_allocates_per_tick(vehicle):
    U = sine_drive_inputs(3000, 0.03, 0.2, 3.0)
    assert U.shape[1] == U_LEN
    counts = allocations(NAMES, U, vehicle)
    for name, (first_ticks, later_ticks) in counts.items():
        # whatever the call itself costs (argument boxing), thousands more ticks add nothing
        assert later_ticks == first_ticks, name
