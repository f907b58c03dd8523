"""Every E2E scheme bit-exact against opendbc's own checksum function (the oracle).

Two levels: slipd.codec.e2e's plain references on random payloads, frame IDs and lengths
(hypothesis), and the numba kernels through a plan compiled from opendbc's DBC of that
platform: a frame whose checksum opendbc computed is accepted, the same frame with one
payload bit flipped is rejected, and a frame slipd encodes carries the checksum opendbc
computes for it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.codec import DecodeState, e2e, kernels
from slipd.codec.plan import _build
from slipd.profile import MessageMap

opendbc = pytest.importorskip("opendbc")
from opendbc import DBC_PATH, get_generated_dbcs  # noqa: E402
from opendbc.car.honda.hondacan import honda_checksum  # noqa: E402
from opendbc.car.hyundai.hyundaicanfd import hkg_can_fd_checksum  # noqa: E402
from opendbc.car.subaru.subarucan import subaru_checksum  # noqa: E402
from opendbc.car.tesla.teslacan import tesla_checksum  # noqa: E402
from opendbc.car.toyota.toyotacan import toyota_checksum  # noqa: E402
from opendbc.car.volkswagen.mqbcan import (  # noqa: E402
    VOLKSWAGEN_MQB_MEB_CONSTANTS,
    volkswagen_mqb_meb_checksum,
)


class _Sig:
    """The ``sig`` argument opendbc's functions take (only its start bit is read)."""

    def __init__(self, start_bit: int):
        self.start_bit = start_bit


payloads = st.integers(0, 2**64 - 1)
FD_LENGTHS = (8, 12, 16, 20, 24, 32, 48, 64)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=1, max_size=8), frame_id=st.integers(0, 0x1FFFFFFF))
def test_honda_reference(data, frame_id):
    assert e2e.honda_checksum(frame_id, data) == honda_checksum(frame_id, None,
                                                                bytearray(data))


@settings(max_examples=300, deadline=None)
@given(length=st.sampled_from(FD_LENGTHS), frame_id=st.integers(0, 0x7FF), data=st.data())
def test_hyundai_kia_canfd_reference(length, frame_id, data):
    payload = data.draw(st.binary(min_size=length, max_size=length))
    assert e2e.hkg_canfd_crc16(frame_id, payload) == hkg_can_fd_checksum(
        frame_id, None, bytearray(payload))


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=8, max_size=8), frame_id=st.integers(0, 0x7FF))
def test_subaru_reference(data, frame_id):
    assert e2e.subaru_checksum(frame_id, data) == subaru_checksum(frame_id, None,
                                                                  bytearray(data))


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=8, max_size=8), frame_id=st.integers(0, 0x7FF),
       crc_byte=st.integers(0, 7))
def test_tesla_reference(data, frame_id, crc_byte):
    assert e2e.tesla_checksum(frame_id, data, crc_byte) == tesla_checksum(
        frame_id, _Sig(8 * crc_byte), bytearray(data))


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=8, max_size=8), frame_id=st.integers(0, 0x7FF))
def test_toyota_reference(data, frame_id):
    assert e2e.toyota_checksum(frame_id, data) == toyota_checksum(frame_id, None,
                                                                  bytearray(data))


@settings(max_examples=300, deadline=None)
@given(data=st.binary(min_size=8, max_size=8),
       frame_id=st.sampled_from(sorted(VOLKSWAGEN_MQB_MEB_CONSTANTS)))
def test_volkswagen_reference(data, frame_id):
    counter = data[1] & 0x0F
    data_id = VOLKSWAGEN_MQB_MEB_CONSTANTS[frame_id][counter]
    assert e2e.autosar_crc8(data, data_id) == volkswagen_mqb_meb_checksum(
        frame_id, None, bytearray(data))


# ---- the kernels, through each platform's own DBC -----------------------------------------

def _dbc(tmp_path_factory, name: str, message: str) -> Path:
    """An opendbc DBC file; of a generated one (some of which cantools refuses as a whole:
    Honda's has an 11-bit ID of 0x33da) the message's own BO_ block as opendbc generates it."""
    plain = Path(DBC_PATH) / f"{name}.dbc"
    if plain.exists():
        return plain
    lines = get_generated_dbcs()[name].splitlines()
    start = next(i for i, line in enumerate(lines)
                 if line.startswith("BO_ ") and line.split()[2] == f"{message}:")
    end = next(i for i in range(start + 1, len(lines)) if not lines[i].strip())
    path = tmp_path_factory.mktemp("opendbc") / f"{name}.dbc"
    path.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: XXX\n\n'
                    + "\n".join(lines[start:end]) + "\n")
    return path


def _oracle(scheme, frame_id, crc_start_bit):
    if scheme == "honda_checksum":
        return lambda d: honda_checksum(frame_id, None, d)
    if scheme == "hkg_canfd_crc16":
        return lambda d: hkg_can_fd_checksum(frame_id, None, d)
    if scheme == "subaru_checksum":
        return lambda d: subaru_checksum(frame_id, None, d)
    if scheme == "tesla_checksum":
        return lambda d: tesla_checksum(frame_id, _Sig(crc_start_bit), d)
    if scheme == "toyota_checksum":
        return lambda d: toyota_checksum(frame_id, None, d)
    return lambda d: volkswagen_mqb_meb_checksum(frame_id, None, d)


CASES = [  # (DBC, message, scheme, checksum signal, counter signal)
    ("honda_civic_hatchback_ex_2017_can_generated", "KINEMATICS", "honda_checksum",
     "CHECKSUM", "COUNTER"),
    ("hyundai_canfd_generated", "WHEEL_SPEEDS", "hkg_canfd_crc16", "CHECKSUM", "COUNTER"),
    ("hyundai_canfd_generated", "STEERING_SENSORS", "hkg_canfd_crc16", "CHECKSUM", "COUNTER"),
    ("hyundai_canfd_generated", "ESP_STATUS", "hkg_canfd_crc16", "CHECKSUM", "COUNTER"),
    ("subaru_global_2017_generated", "Wheel_Speeds", "subaru_checksum", "CHECKSUM",
     "COUNTER"),
    ("tesla_model3_party", "ESP_wheelSpeeds", "tesla_checksum", "ESP_wheelSpeedsChecksum",
     "ESP_wheelSpeedsCounter"),
    ("vw_mqb", "ESP_02", "autosar_crc8", "CHECKSUM", "COUNTER"),
    ("vw_mqb", "LWI_01", "autosar_crc8", "CHECKSUM", "COUNTER"),
]


@pytest.mark.parametrize("dbc_name,message,scheme,crc,counter", CASES,
                         ids=[f"{c[2]}-{c[1]}" for c in CASES])
def test_kernels_agree_with_opendbc(tmp_path_factory, dbc_name, message, scheme, crc, counter):
    from slipd.codec.plan import load_dbc

    path = _dbc(tmp_path_factory, dbc_name, message)
    dbc_message = load_dbc(path).get_message_by_name(message)
    frame_id, length = dbc_message.frame_id, dbc_message.length
    data_ids = tuple(VOLKSWAGEN_MQB_MEB_CONSTANTS.get(frame_id, [0] * 16)) \
        if scheme == "autosar_crc8" else ()
    mmap = MessageMap(message, scheme, 100.0, 0.05, (), crc, counter, data_ids)
    plan = _build(path, [(message, mmap, {})])
    crc_sig = dbc_message.get_signal_by_name(crc)
    oracle = _oracle(scheme, frame_id, crc_sig.start)
    crc_row = int(plan.plan_i[0, kernels.M_CRC_ROW])
    rng = np.random.default_rng(hash(message) % 2**32)
    state = DecodeState.new(1)
    for k in range(200):
        payload = rng.integers(0, 256, length, dtype=np.uint8)
        want = oracle(bytearray(payload.tobytes()))
        kernels._put_raw(plan.plan_i, crc_row, np.uint64(want), payload)
        assert oracle(bytearray(payload.tobytes())) == want  # the field is not covered
        counter_value = kernels._raw(plan.plan_i, int(plan.plan_i[0, kernels.M_COUNTER_ROW]),
                                     payload)
        assert kernels.e2e_code(plan.plan_i, 0, frame_id, payload, length,
                                np.int64(counter_value)) == want
        state.msg_state[:] = (-1.0, -np.inf)  # no counter history: judge the checksum alone
        got = kernels.decode_frame(plan.plan_i, plan.plan_f, plan.lookup, 0, frame_id, False,
                                   length, payload, float(k), plan.timeouts, state.latch,
                                   state.msg_state, state.errors, state.scratch)
        assert got == 0, (k, payload.tobytes().hex())
        # flip one payload bit outside the checksum field
        flipped = payload.copy()
        while True:
            bit = int(rng.integers(0, 8 * length))
            trial = flipped.copy()
            trial[bit // 8] ^= 1 << (bit % 8)
            if kernels._raw(plan.plan_i, crc_row, trial) == kernels._raw(plan.plan_i, crc_row,
                                                                           payload):
                break
        state.msg_state[:] = (-1.0, -np.inf)
        assert kernels.decode_frame(plan.plan_i, plan.plan_f, plan.lookup, 0, frame_id, False,
                                    length, trial, float(k), plan.timeouts, state.latch,
                                    state.msg_state, state.errors, state.scratch) == -2
    # what slipd encodes carries opendbc's checksum
    out = np.zeros(length, dtype=np.uint8)
    for counter_value in range(4):
        kernels.encode_frame(plan.plan_i, plan.plan_f, 0, np.zeros(1), counter_value, out)
        assert kernels._raw(plan.plan_i, crc_row, out) == oracle(bytearray(out.tobytes()))
