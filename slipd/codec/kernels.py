"""numba kernels that execute a compiled codec plan (see :mod:`slipd.codec.plan`).

The plan is three arrays, so a call passes few arguments (each array argument costs a small
allocation in numba's call wrapper):

``plan_i`` int64 [rows, I_COLS]
    one row per message, then one per signal (``M_*`` and ``S_*`` columns);
``plan_f`` float64 [rows, F_COLS]
    scale, offset, range and SI factor per signal row;
``lookup`` int64 [2 + 2048 * n_bus + 2 * n_extended]
    n_bus and n_extended, then (bus, standard ID) -> message row (or -1) at
    ``2 + bus * 2048 + id``, then the sorted keys ``bus << 29 | id`` of the extended IDs and
    their rows.

Signals are read and written bit by bit from the payload bytes (classic frames and CAN FD
frames up to 64 bytes alike): a little-endian (Intel) signal from its start bit upwards, a
big-endian (Motorola) one from its most significant bit in the DBC's "sawtooth" numbering.

Latch and bookkeeping arrays are owned by the caller (daemon or batch engine):

``latch`` float64 [3, N_IN]: newest value, its timestamp, 1.0 while set and available;
``msg_state`` float64 [n_msg, 2]: last alive counter (-1 none), time it was last seen in
sequence (or as the reference after a silence);
``errors`` int64 [n_msg + 1, N_ERR]: per-message counters, the last row for unknown IDs.

A frame that fails a check updates nothing but its error counter. A value its sender marks
as not available (a qualifier bit, a value-table code such as "init" or "fault") makes only
that channel invalid from the frame's time on; the frame's other channels are used.
"""

from __future__ import annotations

import math

import numpy as np

from slipd.codec.calibration import calibrate
from slipd.codec.e2e import CRC8_H2F, CRC8_SAE_J1850, CRC16_XMODEM, HKG_CANFD_XOR
from slipd.numba_cache import nb

MAX_PAYLOAD = 64  # bytes: CAN FD
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
# plan_i columns of a message row
M_FRAME_ID = 0
M_DLC = 1
M_E2E = 2
M_CRC_ROW = 3  # signal row of the CRC/checksum, -1 none
M_COUNTER_ROW = 4  # signal row of the alive counter, -1 none
M_SIG_FIRST = 5
M_SIG_COUNT = 6
M_MAX_DELTA = 7
M_BUS = 8  # bus index (profile bus order)
M_EXTENDED = 9
M_DATA_IDS = 10  # 16 data IDs (autosar_crc8), one per counter value
M_FD = M_DATA_IDS + 16  # 1: a CAN FD frame
# plan_i columns of a signal row
S_START = 0  # little endian: start (LSB) bit; big endian: the MSB's position counted from
#              bit 7 of byte 0 downwards (byte * 8 + 7 - bit)
S_LENGTH = 1
S_BIG_ENDIAN = 2
S_SIGNED = 3
S_FLOAT = 4
S_SLOT = 5  # channel (decode) or value slot (encode), -1 for CRC/counter/sign/qualifier rows
S_ACCUMULATE = 6  # 1: add to the slot (a channel summed from several signals)
S_CHECK_RANGE = 7
S_CRC_BYTE = 8  # for CRC rows: the byte index of the CRC's first byte
S_SIGN_ROW = 9  # row of the sign bit of a sign-magnitude value (1 = negative), -1 none
S_VALID_ROW = 10  # row of the qualifier signal, -1 none
S_VALID_MASK = 11  # bit k set: qualifier raw value k means "valid"
S_N_INVALID = 12  # count of raw values meaning "not available" (value table), then the values
S_INVALID = 13
MAX_INVALID = 12
I_COLS = M_FD + 1

# plan_f columns
F_SCALE = 0
F_OFFSET = 1
F_MIN = 2  # physical range (DBC units); MIN >= MAX means no range check
F_MAX = 3
F_FACTOR = 4  # SI = physical * factor
F_COLS = 5

# E2E scheme ids (slipd.profile.E2E_SCHEMES)
E2E_NONE = 0
E2E_SLIPD_CRC8 = 1
E2E_TOYOTA = 2
E2E_AUTOSAR_CRC8 = 3
E2E_HONDA = 4
E2E_HKG_CANFD = 5
E2E_SUBARU = 6
E2E_TESLA = 7

# error counter columns
ERR_ACCEPTED = 0
ERR_LENGTH = 1
ERR_E2E = 2
ERR_COUNTER_REPEAT = 3
ERR_COUNTER_JUMP = 4
ERR_RANGE = 5
ERR_UNKNOWN_ID = 6
ERR_NOT_AVAILABLE = 7  # an accepted frame's value its sender marked not available
ERR_COUNTER_SYNC = 8  # the counter's reference after a silence (not an error, not used)
N_ERR = 9
ERROR_NAMES = ("accepted", "wrong_length", "e2e", "counter_repeat", "counter_jump",
               "out_of_range", "unknown_id", "not_available", "counter_sync")

LATCH_VALUE = 0
LATCH_TIME = 1
LATCH_SET = 2
BUS_KEY_SHIFT = 29  # extended lookup key: bus << 29 | id
LOOKUP_N_BUS = 0
LOOKUP_N_EXT = 1
LOOKUP_HEADER = 2


@nb.njit(cache=True, inline="always")
def lookup_message(lookup, bus, frame_id, extended):
    """Message row of a frame ID on bus ``bus``, or -1 when the plan does not know it."""
    n_bus = lookup[LOOKUP_N_BUS]
    if bus < 0 or bus >= n_bus:
        return -1
    if not extended:
        if 0 <= frame_id < 2048:
            return lookup[LOOKUP_HEADER + bus * 2048 + frame_id]
        return -1
    n_ext = lookup[LOOKUP_N_EXT]
    keys = LOOKUP_HEADER + n_bus * 2048
    key = (np.int64(bus) << BUS_KEY_SHIFT) | np.int64(frame_id)
    lo = 0
    hi = n_ext - 1
    while lo <= hi:
        mid = (lo + hi) // 2
        probe = lookup[keys + mid]
        if probe == key:
            return lookup[keys + n_ext + mid]
        if probe < key:
            lo = mid + 1
        else:
            hi = mid - 1
    return -1


@nb.njit(cache=True, inline="always")
def _raw(plan_i, row, data):
    """The signal's raw bits (unsigned, right-aligned) from the payload bytes."""
    length = plan_i[row, S_LENGTH]
    position = plan_i[row, S_START]
    value = np.uint64(0)
    got = 0
    if plan_i[row, S_BIG_ENDIAN]:
        # position counts from bit 7 of byte 0 downwards: MSB first
        while got < length:
            index = position >> 3
            available = 8 - (position & 7)
            take = min(available, length - got)
            chunk = (np.uint64(data[index]) >> np.uint64(available - take)) & np.uint64(
                (1 << take) - 1)
            value = (value << np.uint64(take)) | chunk
            got += take
            position += take
    else:
        while got < length:
            index = position >> 3
            offset = position & 7
            take = min(8 - offset, length - got)
            chunk = (np.uint64(data[index]) >> np.uint64(offset)) & np.uint64((1 << take) - 1)
            value |= chunk << np.uint64(got)
            got += take
            position += take
    return value


@nb.njit(cache=True, inline="always")
def _payload_words(data):
    """The payload's first 8 bytes as two uint64 words, (little-endian, big-endian): byte 0
    lowest in the first, highest in the second. Zeros when ``data`` is shorter than 8."""
    le = np.uint64(0)
    be = np.uint64(0)
    if data.shape[0] >= 8:
        for i in range(8):
            b = np.uint64(data[i])
            le |= b << np.uint64(8 * i)
            be = (be << np.uint64(8)) | b
    return le, be


@nb.njit(cache=True, inline="always")
def _raw_words(plan_i, row, data, le, be):
    """:func:`_raw` with the payload's words (:func:`_payload_words`) at hand: one shift and
    mask when the signal lies within the first 8 bytes (every classic frame's signal), else
    the byte loop. In the big-endian word the MSB-first bit index ``i`` (S_START's numbering)
    is bit ``63 - i``, so a signal's LSB at ``start + length - 1`` is bit
    ``64 - start - length``; in the little-endian word bit ``i`` is bit ``i``."""
    length = plan_i[row, S_LENGTH]
    position = plan_i[row, S_START]
    if data.shape[0] < 8 or length >= 64 or position + length > 64:
        return _raw(plan_i, row, data)
    mask = (np.uint64(1) << np.uint64(length)) - np.uint64(1)
    if plan_i[row, S_BIG_ENDIAN]:
        return (be >> np.uint64(64 - position - length)) & mask
    return (le >> np.uint64(position)) & mask


@nb.njit(cache=True, _nrt=False)
def _put_raw(plan_i, row, raw, out):
    """Write the low S_LENGTH bits of ``raw`` into the payload ``out`` at the signal's place."""
    length = plan_i[row, S_LENGTH]
    position = plan_i[row, S_START]
    done = 0
    if plan_i[row, S_BIG_ENDIAN]:
        while done < length:
            index = position >> 3
            available = 8 - (position & 7)
            take = min(available, length - done)
            shift = length - done - take  # bits of raw below this chunk
            chunk = (raw >> np.uint64(shift)) & np.uint64((1 << take) - 1)
            low = available - take
            mask = ((1 << take) - 1) << low
            out[index] = np.uint8((np.int64(out[index]) & ~mask) | (np.int64(chunk) << low))
            done += take
            position += take
    else:
        while done < length:
            index = position >> 3
            offset = position & 7
            take = min(8 - offset, length - done)
            chunk = (raw >> np.uint64(done)) & np.uint64((1 << take) - 1)
            mask = ((1 << take) - 1) << offset
            out[index] = np.uint8((np.int64(out[index]) & ~mask) | (np.int64(chunk) << offset))
            done += take
            position += take


@nb.njit(cache=True, inline="always")
def _ieee(bits, length):
    if length == 32:
        sign = -1.0 if (bits >> np.uint64(31)) & np.uint64(1) else 1.0
        exponent = int((bits >> np.uint64(23)) & np.uint64(0xFF))
        mantissa = int(bits & np.uint64(0x7FFFFF))
        if exponent == 0:
            return sign * math.ldexp(mantissa, -149)
        if exponent == 255:
            return sign * math.inf if mantissa == 0 else math.nan
        return sign * math.ldexp(mantissa | 0x800000, exponent - 150)
    sign = -1.0 if (bits >> np.uint64(63)) & np.uint64(1) else 1.0
    exponent = int((bits >> np.uint64(52)) & np.uint64(0x7FF))
    mantissa = int(bits & np.uint64(0xFFFFFFFFFFFFF))
    if exponent == 0:
        return sign * math.ldexp(mantissa, -1074)
    if exponent == 2047:
        return sign * math.inf if mantissa == 0 else math.nan
    return sign * math.ldexp(mantissa | 0x10000000000000, exponent - 1075)


@nb.njit(cache=True, inline="always")
def _physical_of_raw(plan_i, plan_f, row, raw):
    length = plan_i[row, S_LENGTH]
    if plan_i[row, S_FLOAT]:
        value = _ieee(raw, length)
    elif plan_i[row, S_SIGNED] and length < 64 and (raw >> np.uint64(length - 1)) & np.uint64(1):
        value = float(np.int64(raw) - (np.int64(1) << np.int64(length)))
    elif plan_i[row, S_SIGNED]:
        value = float(np.int64(raw))
    else:
        value = float(raw)
    return value * plan_f[row, F_SCALE] + plan_f[row, F_OFFSET]


@nb.njit(cache=True, _nrt=False)
def signal_physical(plan_i, plan_f, row, data):
    """Physical value (DBC units) of signal ``row`` in a payload, before sign and qualifier."""
    return _physical_of_raw(plan_i, plan_f, row, _raw(plan_i, row, data))


@nb.njit(cache=True, _nrt=False)
def decode_signal(plan_i, plan_f, row, data, dlc):
    """Physical value of one signal row in a payload (tests and diagnostics)."""
    return signal_physical(plan_i, plan_f, row, data)


@nb.njit(cache=True, inline="always")
def _available(plan_i, row, raw, data):
    """False when the sender marks this value as not available: a value-table code of the
    signal, or its qualifier signal outside the valid values."""
    for k in range(plan_i[row, S_N_INVALID]):
        if raw == np.uint64(plan_i[row, S_INVALID + k]):
            return False
    valid_row = plan_i[row, S_VALID_ROW]
    if valid_row >= 0:
        qualifier = np.int64(_raw(plan_i, valid_row, data))
        if qualifier > 62 or not (plan_i[row, S_VALID_MASK] >> qualifier) & 1:
            return False
    return True


@nb.njit(cache=True, inline="always")
def e2e_code(plan_i, msg, frame_id, data, dlc, counter):
    """The CRC/checksum the message's E2E scheme expects for this payload (the opendbc
    functions of the same names, see slipd.codec.e2e)."""
    scheme = plan_i[msg, M_E2E]
    crc_row = plan_i[msg, M_CRC_ROW]
    if scheme == E2E_TOYOTA:
        total = np.int64(dlc)
        address = np.int64(frame_id)
        while address > 0:
            total += address & 0xFF
            address >>= 8
        for i in range(dlc - 1):
            total += data[i]
        return total & 0xFF
    if scheme == E2E_HONDA:
        total = np.int64(0)
        address = np.int64(frame_id)
        while address > 0:
            total += address & 0xF
            address >>= 4
        for i in range(dlc):
            x = np.int64(data[i])
            if i == dlc - 1:
                x >>= 4
            total += (x & 0xF) + (x >> 4)
        total = 8 - total
        if plan_i[msg, M_EXTENDED]:
            total += 3
        return total & 0xF
    if scheme == E2E_HKG_CANFD:
        crc = np.int64(0)
        for i in range(2, dlc):
            crc = ((crc << 8) ^ CRC16_XMODEM[(crc >> 8) ^ data[i]]) & 0xFFFF
        crc = ((crc << 8) ^ CRC16_XMODEM[(crc >> 8) ^ (frame_id & 0xFF)]) & 0xFFFF
        crc = ((crc << 8) ^ CRC16_XMODEM[(crc >> 8) ^ ((frame_id >> 8) & 0xFF)]) & 0xFFFF
        return crc ^ HKG_CANFD_XOR[dlc]
    if scheme == E2E_SUBARU:
        total = np.int64(0)
        address = np.int64(frame_id)
        while address > 0:
            total += address & 0xFF
            address >>= 8
        for i in range(1, dlc):
            total += data[i]
        return total & 0xFF
    crc_byte = plan_i[crc_row, S_CRC_BYTE]
    if scheme == E2E_TESLA:
        total = np.int64((frame_id & 0xFF) + ((frame_id >> 8) & 0xFF))
        for i in range(dlc):
            if i != crc_byte:
                total += data[i]
        return total & 0xFF
    crc = np.int64(0xFF)
    if scheme == E2E_SLIPD_CRC8:
        for i in range(dlc):
            if i != crc_byte:
                crc = np.int64(CRC8_SAE_J1850[crc ^ data[i]])
        crc = np.int64(CRC8_SAE_J1850[crc ^ (frame_id & 0xFF)])
        return crc ^ 0xFF
    # E2E_AUTOSAR_CRC8
    for i in range(dlc):
        if i != crc_byte:
            crc = np.int64(CRC8_H2F[crc ^ data[i]])
    crc = np.int64(CRC8_H2F[crc ^ plan_i[msg, M_DATA_IDS + (counter & 15)]])
    return crc ^ 0xFF


@nb.njit(cache=True, inline="always")
def decode_frame(plan_i, plan_f, lookup, bus, frame_id, extended, dlc, data, t, timeouts,
                 latch, msg_state, errors, scratch):
    """Check one frame received on bus ``bus`` and, if it passes, write its channels into
    ``latch``.

    ``timeouts`` float64 [n_msg]: a message silent for longer resynchronises its counter.
    ``scratch`` float64 [N_IN]: room to assemble channel values before committing them, so a
    frame with one out-of-range signal updates none of its channels.
    Returns the message row (>= 0) when accepted, -1 unknown ID, -2 rejected.
    """
    msg = lookup_message(lookup, bus, frame_id, extended)
    n_msg = errors.shape[0] - 1
    if msg < 0:
        errors[n_msg, ERR_UNKNOWN_ID] += 1
        return -1
    if dlc != plan_i[msg, M_DLC]:
        errors[msg, ERR_LENGTH] += 1
        return -2
    le, be = _payload_words(data)
    counter = np.int64(-1)
    counter_row = plan_i[msg, M_COUNTER_ROW]
    if counter_row >= 0:
        counter = np.int64(_raw_words(plan_i, counter_row, data, le, be))
    if plan_i[msg, M_E2E] != E2E_NONE:
        crc_row = plan_i[msg, M_CRC_ROW]
        if e2e_code(plan_i, msg, frame_id, data, dlc, counter) != np.int64(
            _raw_words(plan_i, crc_row, data, le, be)
        ):
            errors[msg, ERR_E2E] += 1
            return -2
    if counter_row >= 0:
        last = msg_state[msg, 0]
        if last >= 0.0 and t - msg_state[msg, 1] > timeouts[msg]:
            # The first frame after a silence longer than the timeout: its counter is the
            # reference the next one is checked against, so it is not used itself (accepting
            # it unchecked let a stale sender's frame through after every timeout). AUTOSAR
            # E2E's state machine likewise wants frames in sequence before it says OK again.
            # Costs one frame period after an outage. (The very first frame of a message has
            # no history to be stale against and is used, as before.)
            msg_state[msg, 0] = counter
            msg_state[msg, 1] = t
            errors[msg, ERR_COUNTER_SYNC] += 1
            return -2
        if last >= 0.0:
            modulus = 1 << plan_i[counter_row, S_LENGTH]
            delta = (counter - np.int64(last)) % modulus
            if delta == 0:
                # A repeat keeps the sequence (msg_state[msg, 1] is when the counter was last
                # seen): a sender stuck repeating one frame is rejected for as long as it is.
                msg_state[msg, 1] = t
                errors[msg, ERR_COUNTER_REPEAT] += 1
                return -2
            if delta > plan_i[msg, M_MAX_DELTA]:
                # Resynchronise on the new value so one lost sequence costs one frame.
                msg_state[msg, 0] = counter
                msg_state[msg, 1] = t
                errors[msg, ERR_COUNTER_JUMP] += 1
                return -2
    first = plan_i[msg, M_SIG_FIRST]
    unavailable = np.int64(0)  # bit per slot: a value marked not available in this frame
    for row in range(first, first + plan_i[msg, M_SIG_COUNT]):
        slot = plan_i[row, S_SLOT]
        if slot < 0:
            continue
        raw = _raw_words(plan_i, row, data, le, be)
        physical = _physical_of_raw(plan_i, plan_f, row, raw)
        if (plan_i[row, S_N_INVALID] > 0 or plan_i[row, S_VALID_ROW] >= 0) and not _available(
                plan_i, row, raw, data):
            unavailable |= np.int64(1) << slot
            continue
        if plan_i[row, S_CHECK_RANGE] and plan_f[row, F_MIN] < plan_f[row, F_MAX]:
            tolerance = 0.5 * abs(plan_f[row, F_SCALE])
            if not (plan_f[row, F_MIN] - tolerance <= physical <= plan_f[row, F_MAX] + tolerance):
                errors[msg, ERR_RANGE] += 1
                return -2
        if not math.isfinite(physical):
            errors[msg, ERR_RANGE] += 1
            return -2
        sign_row = plan_i[row, S_SIGN_ROW]
        if sign_row >= 0 and _raw_words(plan_i, sign_row, data, le, be) != np.uint64(0):
            physical = -physical
        if plan_i[row, S_ACCUMULATE]:
            scratch[slot] += physical * plan_f[row, F_FACTOR]
        else:
            scratch[slot] = physical * plan_f[row, F_FACTOR]
    for row in range(first, first + plan_i[msg, M_SIG_COUNT]):
        slot = plan_i[row, S_SLOT]
        if slot < 0:
            continue
        latch[LATCH_TIME, slot] = t
        if (unavailable >> slot) & 1:
            latch[LATCH_SET, slot] = 0.0  # invalid from now on; the old value stays
        else:
            latch[LATCH_VALUE, slot] = scratch[slot]
            latch[LATCH_SET, slot] = 1.0
    if unavailable:
        errors[msg, ERR_NOT_AVAILABLE] += 1
    if counter_row >= 0:
        msg_state[msg, 0] = counter
    msg_state[msg, 1] = t
    errors[msg, ERR_ACCEPTED] += 1
    return msg


#: s: how far a latched value may be stamped after the tick that samples it and still count
#: as fresh. Never, in a replay (a tick latches the frames up to its time) nor in the daemon
#: (its frames are on its own time base, slipd.daemon.loop); a frame from the future is one
#: stamped across a wall-clock step, whose age is unknown: counted as fresh it stays valid
#: for as long as the step, so it is stale. The microsecond covers the recorder's rounding.
FUTURE_TOLERANCE_S = 1e-6


@nb.njit(cache=True, _nrt=False)
def sample_latch(latch, channel_timeouts, calibration, t, u):
    """Sample-and-hold of the latch at tick time ``t`` into the input vector ``u``.

    A channel is valid when it has been set and its newest value is at most its timeout old
    (and not stamped after ``t``: FUTURE_TOLERANCE_S).
    Last, the profile's sensor-error corrections (``calibration``, float64 [CAL_LEN], see
    slipd.codec.calibration; inactive without a [calibration] table).
    """
    n_in = latch.shape[1]
    for ch in range(n_in):
        age = t - latch[LATCH_TIME, ch]
        valid = (latch[LATCH_SET, ch] > 0.5 and age <= channel_timeouts[ch]
                 and age >= -FUTURE_TOLERANCE_S)
        u[ch] = latch[LATCH_VALUE, ch]
        u[n_in + ch] = 1.0 if valid else 0.0
    u[2 * n_in] = t
    calibrate(calibration, u)


@nb.njit(cache=True, nogil=True, _nrt=False)
def latch_ticks(plan_i, plan_f, lookup, timeouts, channel_timeouts, calibration, frame_time,
                frame_bus, frame_id, frame_flags, frame_dlc, frame_data, tick_time, tick_until,
                latch, msg_state, errors, scratch, U):
    """The batch engine's front half: decode frames in log order and sample at every tick.

    Frames ``[.., tick_until[k])`` are applied before tick ``k`` is sampled at ``tick_time[k]``
    (the daemon's order: what was received before the tick is latched, then the tick
    samples; from a log's times that is ``searchsorted(frame_time, tick_time, 'right')``, from
    a flight recorder it is the file order). ``frame_bus`` is each frame's bus index (-1: a
    channel the profile does not read, skipped). ``frame_flags`` bit 0 = extended ID, bit 1 =
    remote, bit 2 = error frame (the last two are never decoded). ``scratch`` is
    decode_frame's (float64 [N_IN], DecodeState.scratch). Returns frames consumed.
    """
    i = 0
    for k in range(tick_time.shape[0]):
        while i < tick_until[k]:
            flags = frame_flags[i]
            if not (flags & 6) and frame_bus[i] >= 0:
                decode_frame(plan_i, plan_f, lookup, frame_bus[i], frame_id[i],
                             (flags & 1) != 0, frame_dlc[i], frame_data[i], frame_time[i],
                             timeouts, latch, msg_state, errors, scratch)
            i += 1
        sample_latch(latch, channel_timeouts, calibration, tick_time[k], U[k])
    return i


@nb.njit(cache=True, _nrt=False)
def _raw_of_physical(plan_i, plan_f, row, physical):
    """Raw integer bits of a physical value: clamped to the DBC range and the bit width."""
    length = plan_i[row, S_LENGTH]
    if plan_f[row, F_MIN] < plan_f[row, F_MAX]:
        physical = min(max(physical, plan_f[row, F_MIN]), plan_f[row, F_MAX])
    if plan_i[row, S_FLOAT]:
        # Float signals are written by the Python encoder path (rare on buses); not here.
        return np.uint64(0)
    scaled = (physical - plan_f[row, F_OFFSET]) / plan_f[row, F_SCALE]
    if not math.isfinite(scaled):
        scaled = 0.0
    value = round(scaled)
    if plan_i[row, S_SIGNED]:
        low = -(2.0 ** (length - 1))
        high = 2.0 ** (length - 1) - 1.0
    else:
        low = 0.0
        high = 2.0**length - 1.0
    value = min(max(value, low), high)
    return np.uint64(np.int64(value))


@nb.njit(cache=True, _nrt=False)
def encode_frame(plan_i, plan_f, msg, values, counter, out):
    """Encode message row ``msg`` from ``values`` (SI, by slot) into ``out`` (uint8[>= dlc]).

    Values are converted to physical units, clamped to the signal's DBC range and bit width
    (cantools' non-strict encode overflows instead) and rounded to the DBC resolution; signals
    summed into one channel are filled in order, each taking what the previous left over. A
    sign-magnitude value writes its magnitude and its sign bit, a qualified one its qualifier's
    first valid value. The alive counter and the CRC/checksum are filled last.
    """
    dlc = plan_i[msg, M_DLC]
    for i in range(dlc):
        out[i] = 0
    first = plan_i[msg, M_SIG_FIRST]
    remainder = 0.0
    for row in range(first, first + plan_i[msg, M_SIG_COUNT]):
        slot = plan_i[row, S_SLOT]
        if slot < 0:
            continue
        if plan_i[row, S_ACCUMULATE]:
            physical = remainder
        else:
            physical = values[slot] / plan_f[row, F_FACTOR]
        sign_row = plan_i[row, S_SIGN_ROW]
        negative = False
        if sign_row >= 0:
            negative = physical < 0.0
            physical = abs(physical)
            _put_raw(plan_i, sign_row, np.uint64(1 if negative else 0), out)
        valid_row = plan_i[row, S_VALID_ROW]
        if valid_row >= 0:
            mask = plan_i[row, S_VALID_MASK]
            first_valid = 0
            while first_valid < 62 and not (mask >> first_valid) & 1:
                first_valid += 1
            _put_raw(plan_i, valid_row, np.uint64(first_valid), out)
        raw = _raw_of_physical(plan_i, plan_f, row, physical)
        _put_raw(plan_i, row, raw, out)
        sent = signal_physical(plan_i, plan_f, row, out)
        remainder = (-physical if negative else physical) - (-sent if negative else sent)
    counter_row = plan_i[msg, M_COUNTER_ROW]
    if counter_row >= 0:
        _put_raw(plan_i, counter_row, np.uint64(counter), out)
    if plan_i[msg, M_E2E] != E2E_NONE:
        crc_row = plan_i[msg, M_CRC_ROW]
        code = e2e_code(plan_i, msg, plan_i[msg, M_FRAME_ID], out, dlc, counter)
        _put_raw(plan_i, crc_row, np.uint64(code), out)


@nb.njit(cache=True, _nrt=False)
def encode_rows(plan_i, plan_f, msg, values, first_counter, out):
    """Encode one frame per row of ``values`` [n, slots] into ``out`` [n, dlc]."""
    counter_row = plan_i[msg, M_COUNTER_ROW]
    modulus = 1 << plan_i[counter_row, S_LENGTH] if counter_row >= 0 else 1
    for k in range(values.shape[0]):
        encode_frame(plan_i, plan_f, msg, values[k], (first_counter + k) % modulus, out[k])
