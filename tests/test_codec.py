"""The compiled codec against cantools, E2E checks and the production (Toyota) profile."""

from __future__ import annotations

import math

import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.channels import VALID, In, new_u
from slipd.codec import Codec, Tx, e2e, kernels
from slipd.codec.calibration import calibration_vector
from slipd.codec.plan import OUTPUT_MESSAGES, compile_input_plan, compile_output_plan
from slipd.profile import Calibration, load_profile

DEFAULT = load_profile("default")
TOYOTA = load_profile("toyota_prius")


def _all_signal_plan(profile, dbc_path, names):
    """A plan decoding every signal of ``names`` into slots 0.., to compare with cantools."""
    db = cantools.database.load_file(str(dbc_path), strict=False)
    specs = []
    slots = {}
    for name in names:
        message = db.get_message_by_name(name)
        signals = {}
        for signal in message.signals:
            slots[(name, signal.name)] = len(slots)
            signals[signal.name] = (slots[(name, signal.name)] % 64, 1.0, None, None, False,
                                    False)
        specs.append((name, None, signals))
    return db, specs, slots


def _physical(plan, row, payload):
    return kernels.decode_signal(plan.plan_i, plan.plan_f, row, payload, len(payload))


@pytest.mark.parametrize(
    "dbc_path,names",
    [
        (DEFAULT.dbc_path, list(DEFAULT.messages) + list(OUTPUT_MESSAGES)),
        (TOYOTA.dbc_path, list(TOYOTA.messages)),
        (load_profile("vw_golf_mk7").dbc_path, ["ESP_02", "LWI_01", "ESP_19", "ESP_21"]),
        (load_profile("hyundai_ioniq_5").dbc_path,  # CAN FD: 16, 24 and 32 bytes, 64-bit
         ["STEERING_SENSORS", "WHEEL_SPEEDS", "ESC_02_10ms", "IMU_01_10ms"]),
    ],
    ids=["slipd.dbc", "toyota_2017.dbc", "vw_mqb.dbc", "hyundai_canfd.dbc"],
)
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_decode_bit_exact_against_cantools(dbc_path, names, data):
    db, specs, _ = _all_signal_plan(None, dbc_path, names)
    # e2e "none" here: every signal (CRC and counter included) is read as a plain signal.
    for name, _, signals in specs:
        message = db.get_message_by_name(name)
        payload = np.frombuffer(data.draw(st.binary(min_size=message.length,
                                                    max_size=message.length)), dtype=np.uint8)
        expected = message.decode(bytes(payload), decode_choices=False, scaling=True)
        plan = _single_plan(dbc_path, name, signals)
        first = plan.plan_i[0, kernels.M_SIG_FIRST]
        for offset in range(plan.plan_i[0, kernels.M_SIG_COUNT]):
            row = first + offset
            signal = message.signals[offset]
            got = _physical(plan, row, payload)
            want = float(expected[signal.name])
            assert got == pytest.approx(want, rel=1e-12, abs=1e-9), (name, signal.name)


def _single_plan(dbc_path, name, signals):
    from slipd.codec.plan import _build
    from slipd.profile import MessageMap

    mmap = MessageMap(name, "none", 100.0, 0.05, ())
    return _build(dbc_path, [(name, mmap, signals)])


@settings(max_examples=100, deadline=None)
@given(
    ax=st.floats(-30, 30), ay=st.floats(-30, 30), az=st.floats(-30, 30),
    yaw=st.floats(-2.5, 2.5), steer=st.floats(-0.5, 0.5),
    wheel=st.floats(0, 70),
)
def test_encode_decode_round_trip(ax, ay, az, yaw, steer, wheel):
    codec = Codec(DEFAULT)
    db = cantools.database.load_file(str(DEFAULT.dbc_path))
    values = {
        "IMU_ACCEL": {In.AX: ax, In.AY: ay, In.AZ: az},
        "IMU_RATE": {In.YAW_RATE: yaw, In.ROLL_RATE: -yaw / 3, In.PITCH_RATE: yaw / 5},
        "STEERING": {In.STEER: steer, In.STEER_RATE: steer * 2},
        "WHEEL_SPEEDS": {c: wheel for c in (In.WHEEL_SPEED_FL, In.WHEEL_SPEED_FR,
                                            In.WHEEL_SPEED_RL, In.WHEEL_SPEED_RR)},
    }
    t = 0.0
    for message, channels in values.items():
        frame_id, payload = codec.encode_channels(message, {c: np.array([v])
                                                            for c, v in channels.items()})
        decoded = db.decode_message(frame_id, bytes(payload[0]))
        assert decoded[f"{message}_CRC"] == e2e.slipd_crc8(frame_id, bytes(payload[0]))
        assert codec.decode(frame_id, payload[0], t) >= 0
        t += 0.001
    u = codec.sample(t, new_u())
    resolution = {In.AX: 0.001, In.AY: 0.001, In.AZ: 0.001,
                  In.YAW_RATE: math.radians(0.005), In.STEER: math.radians(0.05) / 16,
                  In.WHEEL_SPEED_FL: 0.03125 / 3.6}
    for channels in values.values():
        for channel, value in channels.items():
            step = resolution.get(channel, 1e-2)
            assert u[VALID + channel] == 1.0
            assert abs(u[channel] - value) <= 0.51 * step + 1e-12, channel


def test_encode_clamps_to_signal_range():
    codec = Codec(DEFAULT)
    frame_id, payload = codec.encode_channels("IMU_ACCEL", {In.AX: np.array([1e6]),
                                                            In.AY: np.array([-1e6]),
                                                            In.AZ: np.array([np.nan])})
    decoded = cantools.database.load_file(str(DEFAULT.dbc_path)).decode_message(
        frame_id, bytes(payload[0]))
    assert decoded["ACCEL_X"] == pytest.approx(32.767)
    assert decoded["ACCEL_Y"] == pytest.approx(-32.768)


def _imu_frames(codec, n):
    return codec.encode_channels("IMU_ACCEL", {In.AX: np.full(n, 1.0), In.AY: np.full(n, 2.0),
                                               In.AZ: np.full(n, 9.81)})


def test_e2e_failures_are_counted_and_not_used():
    codec = Codec(DEFAULT)
    frame_id, payload = _imu_frames(codec, 6)
    assert codec.decode(frame_id, payload[0], 0.00) >= 0
    bad_crc = payload[1].copy()
    bad_crc[4] ^= 0x10
    assert codec.decode(frame_id, bad_crc, 0.01) == -2  # CRC mismatch
    assert codec.decode(frame_id, payload[0], 0.02) == -2  # counter repeat
    assert codec.decode(frame_id, payload[3], 0.03) == -2  # counter jump 0 -> 3
    assert codec.decode(frame_id, payload[4], 0.04) >= 0  # in sequence after the jump
    assert codec.decode(frame_id, payload[5][:7], 0.05) == -2  # wrong length
    assert codec.decode(0x7AB, payload[5], 0.05) == -1  # unknown ID
    counts = codec.error_counts()
    assert counts["IMU_ACCEL"] == {"accepted": 2, "wrong_length": 1, "e2e": 1,
                                   "counter_repeat": 1, "counter_jump": 1, "out_of_range": 0,
                                   "unknown_id": 0, "not_available": 0, "counter_sync": 0}
    assert counts["unknown"]["unknown_id"] == 1


def test_crc_covers_frame_id():
    codec = Codec(DEFAULT)
    frame_id, payload = _imu_frames(codec, 1)
    # the same payload under the IMU_RATE ID fails its check (data ID = ID low byte)
    imu_rate_id = 0x101
    assert codec.decode(imu_rate_id, payload[0], 0.0) == -2
    assert codec.error_counts()["IMU_RATE"]["e2e"] == 1


def test_stale_channel_becomes_invalid_after_its_timeout():
    codec = Codec(DEFAULT)
    frame_id, payload = _imu_frames(codec, 1)
    codec.decode(frame_id, payload[0], 1.0)
    timeout = DEFAULT.channels[In.AX].timeout
    assert codec.sample(1.0 + timeout - 1e-9, new_u())[VALID + In.AX] == 1.0
    assert codec.sample(1.0 + timeout + 0.001, new_u())[VALID + In.AX] == 0.0


def test_counter_resynchronises_after_a_silence():
    """After a silence the first frame is the counter's new reference, not used: accepting
    it unchecked let any value through after every timeout."""
    codec = Codec(DEFAULT)
    frame_id, payload = _imu_frames(codec, 6)
    assert codec.decode(frame_id, payload[0], 0.0) >= 0  # the very first: no history
    assert codec.decode(frame_id, payload[1], 0.01) >= 0
    assert codec.decode(frame_id, payload[4], 1.0) == -2  # silent > timeout: a reference
    assert codec.decode(frame_id, payload[5], 1.01) >= 0  # in sequence with it: used
    assert codec.error_counts()["IMU_ACCEL"]["counter_sync"] == 1


def test_a_sender_stuck_repeating_one_frame_is_never_accepted_again():
    """A frozen ECU repeating its last frame: before, its frame was accepted again after
    every timeout (the counter check was skipped for a silent message), so the stale value
    kept its channel fresh."""
    codec = Codec(DEFAULT)
    frame_id, payload = _imu_frames(codec, 3)
    for k in range(3):  # in sequence: in use
        codec.decode(frame_id, payload[k], 0.01 * k)
    accepted = [codec.decode(frame_id, payload[2], 0.03 + 0.01 * k) for k in range(300)]
    assert max(accepted) == -2
    timeout = DEFAULT.channels[In.AX].timeout
    assert codec.sample(3.0, new_u())[VALID + In.AX] == 0.0 and timeout < 2.9
    assert codec.error_counts()["IMU_ACCEL"]["counter_repeat"] == 300


def test_out_of_range_raw_value_is_rejected():
    codec = Codec(TOYOTA)
    db = cantools.database.load_file(str(TOYOTA.dbc_path), strict=False)
    message = db.get_message_by_name("KINEMATICS")
    good = message.encode({"YAW_RATE": 10.0, "ACCEL_X": 1.0, "ACCEL_Y": -2.0}, strict=False)
    assert codec.decode(message.frame_id, good, 0.0) >= 0
    u = codec.sample(0.0, new_u())
    assert u[In.YAW_RATE] == pytest.approx(math.radians(message.decode(good)["YAW_RATE"]))
    # Every raw value of KINEMATICS is inside the profile's range, so narrow the range to
    # make an out-of-range frame.
    from dataclasses import replace

    narrow_channel = replace(TOYOTA.channels[In.AX], signals=tuple(
        replace(s, minimum=-5.0, maximum=5.0) for s in TOYOTA.channels[In.AX].signals))
    narrow = replace(TOYOTA, channels={**TOYOTA.channels, In.AX: narrow_channel})
    codec = Codec(narrow)
    hard = message.encode({"YAW_RATE": 10.0, "ACCEL_X": 9.0, "ACCEL_Y": -2.0}, strict=False)
    assert codec.decode(message.frame_id, hard, 0.0) == -2
    assert codec.error_counts()["KINEMATICS"]["out_of_range"] == 1


def test_toyota_frames_from_cantools_decode_through_the_profile():
    """Frames encoded by cantools from the production DBC (valid checksums) decode exactly."""
    codec = Codec(TOYOTA)
    db = cantools.database.load_file(str(TOYOTA.dbc_path), strict=False)
    rng = np.random.default_rng(1)
    for k in range(50):
        t = k * 0.0125
        speed_kph = float(rng.uniform(0, 200))
        speed = db.get_message_by_name("SPEED")
        payload = bytearray(speed.encode({"ENCODER": k % 256, "SPEED": speed_kph,
                                          "CHECKSUM": 0}, strict=False))
        payload[7] = e2e.toyota_checksum(speed.frame_id, payload)
        assert codec.decode(speed.frame_id, bytes(payload), t) >= 0
        steer = db.get_message_by_name("STEER_ANGLE_SENSOR")
        steer_payload = steer.encode({"STEER_ANGLE": float(rng.integers(-300, 300)) * 1.5,
                                      "STEER_FRACTION": 0.3, "STEER_RATE": 12.0}, strict=False)
        assert codec.decode(steer.frame_id, steer_payload, t) >= 0
        wheels = db.get_message_by_name("WHEEL_SPEEDS")
        wheel_payload = wheels.encode({f"WHEEL_SPEED_{w}": speed_kph for w in
                                       ("FL", "FR", "RL", "RR")}, strict=False)
        assert codec.decode(wheels.frame_id, wheel_payload, t) >= 0
        u = codec.sample(t, new_u())
        assert u[In.SPEED_REF] == pytest.approx(
            speed.decode(bytes(payload))["SPEED"] / 3.6, abs=1e-12)
        decoded_steer = steer.decode(steer_payload)
        assert u[In.STEER] == pytest.approx(
            math.radians(decoded_steer["STEER_ANGLE"] + decoded_steer["STEER_FRACTION"])
            / 15.74, abs=1e-12)
        assert u[In.WHEEL_SPEED_RL] == pytest.approx(
            wheels.decode(wheel_payload)["WHEEL_SPEED_RL"] / 3.6, abs=1e-12)
        corrupted = bytearray(payload)
        corrupted[7] ^= 0x01
        assert codec.decode(speed.frame_id, bytes(corrupted), t + 0.001) == -2
    assert codec.error_counts()["SPEED"]["e2e"] == 50


def test_autosar_crc8_matches_volkswagen_reference():
    # VW MQB LWI_01 (0x86): data ID 0x86 for every counter (opendbc's constants table).
    payload = bytearray([0x00, 0x03, 0x12, 0x34, 0x56, 0x78, 0x9A, 0xBC])
    crc = 0xFF
    for byte in payload[1:]:
        crc = int(e2e.CRC8_H2F[crc ^ byte])
    crc = int(e2e.CRC8_H2F[crc ^ 0x86]) ^ 0xFF  # opendbc volkswagen_mqb_meb_checksum
    assert e2e.autosar_crc8(payload, 0x86) == crc
    # AUTOSAR CRC8H2F check value: "123456789" -> 0xDF
    assert e2e.crc8(e2e.CRC8_H2F, b"123456789") == 0xDF
    # SAE J1850 check value: "123456789" -> 0x4B
    assert e2e.crc8(e2e.CRC8_SAE_J1850, b"123456789") == 0x4B


def test_output_frames_decode_with_cantools():
    codec = Codec(DEFAULT)
    db = cantools.database.load_file(str(DEFAULT.dbc_path))
    values = np.zeros(len(Tx))
    values[Tx.BETA] = math.radians(3.21)
    values[Tx.VX] = 22.5
    values[Tx.VY] = 1.26
    values[Tx.STATUS] = 1
    out = np.zeros(8, dtype=np.uint8)
    frame_id = codec.encode_output("SLIPD_STATE", values, out)
    decoded = db.decode_message(frame_id, bytes(out))
    assert decoded["BETA"] == pytest.approx(3.21, abs=0.0025)
    assert decoded["VX"] == pytest.approx(22.5, abs=0.01)
    assert decoded["STATUS"] == 1
    assert decoded["SLIPD_STATE_CRC"] == e2e.slipd_crc8(frame_id, bytes(out))
    frame_id = codec.encode_output("SLIPD_STATE", values, out)
    assert db.decode_message(frame_id, bytes(out))["SLIPD_STATE_Counter"] == 1


def test_multiplexed_messages_are_rejected(tmp_path):
    from slipd.errors import CodecError

    dbc = tmp_path / "mux.dbc"
    dbc.write_text(
        'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n'
        "BO_ 100 MUXED: 8 A\n"
        ' SG_ SEL M : 0|8@1+ (1,0) [0|255] "" A\n'
        ' SG_ VAL0 m0 : 8|16@1+ (1,0) [0|65535] "" A\n'
    )
    from slipd.codec.plan import _build
    from slipd.profile import MessageMap

    with pytest.raises(CodecError, match="multiplexed"):
        _build(dbc, [("MUXED", MessageMap("MUXED", "none", 10.0, 0.5, ()), {})])


def test_input_plan_compiles_for_shipped_profiles():
    for profile in (DEFAULT, TOYOTA):
        plan = compile_input_plan(profile)
        assert plan.n_messages == len(profile.messages)
    assert compile_output_plan().n_messages == 3


def test_value_table_codes_mark_a_value_not_available(tmp_path):
    """A raw value the DBC's value table names "Init"/"not available" invalidates the channel
    at once (the frame's other channels are used); an explicit invalid_values list wins."""
    from dataclasses import replace

    from slipd.codec.plan import _build, input_signal_specs

    dbc = tmp_path / "vt.dbc"
    dbc.write_text(
        'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n'
        "BO_ 100 RATES: 8 A\n"
        ' SG_ YAW : 0|16@1- (0.01,0) [-300|300] "deg/s" A\n'
        ' SG_ AY : 16|16@1- (0.001,0) [-30|30] "m/s^2" A\n\n'
        'VAL_ 100 YAW 32767 "Init" 32766 "Signal not available" 0 "zero" ;\n')
    profile = replace(DEFAULT, dbc_path=dbc)
    specs = input_signal_specs(DEFAULT)  # reuse the SignalSpec shape of a real channel
    yaw_spec = next(v for _, _, sigs in specs for k, v in sigs.items() if k == "YAW_RATE")
    ay_spec = next(v for _, _, sigs in specs for k, v in sigs.items() if k == "ACCEL_Y")
    from slipd.profile import MessageMap

    mmap = MessageMap("RATES", "none", 100.0, 0.05, ())
    for invalid, codes in ((None, (32766, 32767)), ((5,), (5,))):
        plan = _build(dbc, [("RATES", mmap, {
            "YAW": replace(yaw_spec, factor=math.radians(1.0), invalid_values=invalid),
            "AY": replace(ay_spec, factor=1.0)})])
        row = plan.plan_i[0, kernels.M_SIG_FIRST]
        n = plan.plan_i[row, kernels.S_N_INVALID]
        assert tuple(plan.plan_i[row, kernels.S_INVALID:kernels.S_INVALID + n]) == codes
    plan = _build(dbc, [("RATES", mmap, {
        "YAW": replace(yaw_spec, factor=math.radians(1.0), invalid_values=None),
        "AY": replace(ay_spec, factor=1.0)})])
    from slipd.codec import DecodeState

    state = DecodeState.new(1)
    u = new_u()

    def decode(raw_yaw, t):
        payload = np.zeros(8, np.uint8)
        payload[0:2] = np.frombuffer(int(raw_yaw).to_bytes(2, "little", signed=True), np.uint8)
        payload[2:4] = np.frombuffer((1500).to_bytes(2, "little", signed=True), np.uint8)
        got = kernels.decode_frame(plan.plan_i, plan.plan_f, plan.lookup, 0, 100, False, 8,
                                   payload, t, plan.timeouts, state.latch, state.msg_state,
                                   state.errors, state.scratch)
        timeouts = np.full(len(u) // 2, 1.0)
        kernels.sample_latch(state.latch, timeouts, calibration_vector(Calibration()), t, u)
        return got

    assert decode(1000, 0.0) == 0 and u[VALID + In.YAW_RATE] == 1.0
    assert u[In.YAW_RATE] == pytest.approx(math.radians(10.0))
    assert decode(32767, 0.01) == 0  # "Init": accepted frame, yaw invalid, ay fresh
    assert u[VALID + In.YAW_RATE] == 0.0 and u[VALID + In.AY] == 1.0
    assert u[In.AY] == pytest.approx(1.5)
    assert state.errors[0, kernels.ERR_NOT_AVAILABLE] == 1
    assert decode(1100, 0.02) == 0 and u[VALID + In.YAW_RATE] == 1.0
    assert profile.dbc_path == dbc


@settings(max_examples=300, deadline=None)
@given(start=st.integers(0, 511), length=st.integers(1, 64), big_endian=st.booleans(),
       payload=st.binary(min_size=8, max_size=64))
def test_word_extraction_equals_the_byte_loop(start, length, big_endian, payload):
    """decode_frame reads a signal inside the first 8 bytes from the payload's two words
    (one shift and mask); every other signal through the byte loop: both give _raw's bits."""
    position = start % (len(payload) * 8 - length + 1) if length <= len(payload) * 8 else 0
    plan_i = np.zeros((1, kernels.I_COLS), dtype=np.int64)
    plan_i[0, kernels.S_START] = position
    plan_i[0, kernels.S_LENGTH] = length
    plan_i[0, kernels.S_BIG_ENDIAN] = int(big_endian)
    data = np.frombuffer(payload, dtype=np.uint8).copy()
    le, be = (np.uint64(w) for w in kernels._payload_words(data))
    assert kernels._raw_words(plan_i, 0, data, le, be) == kernels._raw(plan_i, 0, data)
    short = data[:7]  # shorter than a word: the byte loop
    if position + length <= 56:
        le, be = (np.uint64(w) for w in kernels._payload_words(short))
        assert kernels._raw_words(plan_i, 0, short, le, be) == kernels._raw(plan_i, 0, short)


def test_an_output_plan_is_compiled_once_per_layout_and_dbc_version(tmp_path):
    """compile_output_plan is memoised on the DBC file's version and the output layout: the
    same layout gets the same plan, another ID, bus or format its own, an edited DBC a new
    one."""
    import os
    import shutil

    from slipd.codec.plan import SLIPD_DBC
    from slipd.profile import OutputMap

    nominal = compile_output_plan(outputs=OutputMap())
    assert compile_output_plan(outputs=OutputMap()) is nominal
    moved = compile_output_plan(outputs=OutputMap(frame_ids={"SLIPD_STATE": 0x6F0}))
    assert moved is not nominal and moved.frame_id("SLIPD_STATE") == 0x6F0
    assert nominal.frame_id("SLIPD_STATE") != 0x6F0
    assert compile_output_plan(outputs=OutputMap(bus="chassis")).buses == ("chassis",)
    assert compile_output_plan(outputs=OutputMap(extended=True)).is_extended("SLIPD_STATE")
    copy = tmp_path / "slipd.dbc"
    shutil.copy(SLIPD_DBC, copy)
    first = compile_output_plan(copy)
    stat = copy.stat()
    os.utime(copy, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert compile_output_plan(copy) is not first
