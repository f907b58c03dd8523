"""numba kernels that execute a compiled codec plan (see :mod:`slipd.codec.plan`).

The plan is three arrays, so a call passes few arguments (each array argument costs a small
allocation in numba's call wrapper):

``plan_i`` int64 [rows, I_COLS]
    one row per message, then one per signal (``M_*`` and ``S_*`` columns);
``plan_f`` float64 [rows, F_COLS]
    scale, offset, range and SI factor per signal row;
``lookup`` int64 [2048 + 2 * n_extended]
    standard ID -> message row (or -1), then the sorted extended IDs and their rows.

Latch and bookkeeping arrays are owned by the caller (daemon or batch engine):

``latch`` float64 [3, N_IN]: newest value, its timestamp, 1.0 once set;
``msg_state`` float64 [n_msg, 2]: last alive counter (-1 none), time of the last accepted frame;
``errors`` int64 [n_msg + 1, N_ERR]: per-message counters, the last row for unknown IDs.

A frame that fails a check updates nothing but its error counter.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from slipd.codec.e2e import CRC8_H2F, CRC8_SAE_J1850

# plan_i columns of a message row
M_FRAME_ID = 0
M_DLC = 1
M_E2E = 2
M_CRC_ROW = 3  # signal row of the CRC/checksum byte, -1 none
M_COUNTER_ROW = 4  # signal row of the alive counter, -1 none
M_SIG_FIRST = 5
M_SIG_COUNT = 6
M_MAX_DELTA = 7
M_DATA_ID_FIRST = 8  # 16 data IDs follow in plan_i[row, M_DATA_IDS:]
M_EXTENDED = 9
M_DATA_IDS = 10
# plan_i columns of a signal row
S_SHIFT = 0  # right shift in the little-endian (Intel) or big-endian (Motorola) 64-bit word
S_LENGTH = 1
S_BIG_ENDIAN = 2
S_SIGNED = 3
S_FLOAT = 4
S_SLOT = 5  # channel (decode) or value slot (encode), -1 for CRC/counter rows
S_ACCUMULATE = 6  # 1: add to the slot (a channel summed from several signals)
S_CHECK_RANGE = 7
S_CRC_BYTE = 8  # for CRC rows: the byte index
I_COLS = M_DATA_IDS + 16

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

# error counter columns
ERR_ACCEPTED = 0
ERR_LENGTH = 1
ERR_E2E = 2
ERR_COUNTER_REPEAT = 3
ERR_COUNTER_JUMP = 4
ERR_RANGE = 5
ERR_UNKNOWN_ID = 6
N_ERR = 7
ERROR_NAMES = ("accepted", "wrong_length", "e2e", "counter_repeat", "counter_jump",
               "out_of_range", "unknown_id")

LATCH_VALUE = 0
LATCH_TIME = 1
LATCH_SET = 2


@nb.njit(cache=True)
def lookup_message(lookup, frame_id, extended):
    """Message row of a frame ID, or -1 when the plan does not know it."""
    if not extended:
        if 0 <= frame_id < 2048:
            return lookup[frame_id]
        return -1
    n_ext = (lookup.shape[0] - 2048) // 2
    lo = 0
    hi = n_ext - 1
    while lo <= hi:
        mid = (lo + hi) // 2
        key = lookup[2048 + mid]
        if key == frame_id:
            return lookup[2048 + n_ext + mid]
        if key < frame_id:
            lo = mid + 1
        else:
            hi = mid - 1
    return -1


@nb.njit(cache=True)
def _words(data, dlc):
    little = np.uint64(0)
    big = np.uint64(0)
    for i in range(min(dlc, 8)):
        byte = np.uint64(data[i])
        little |= byte << np.uint64(8 * i)
        big |= byte << np.uint64(56 - 8 * i)
    return little, big


@nb.njit(cache=True)
def _raw(plan_i, row, little, big):
    length = plan_i[row, S_LENGTH]
    word = big if plan_i[row, S_BIG_ENDIAN] else little
    value = word >> np.uint64(plan_i[row, S_SHIFT])
    if length < 64:
        value &= (np.uint64(1) << np.uint64(length)) - np.uint64(1)
    return value


@nb.njit(cache=True)
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


@nb.njit(cache=True)
def signal_physical(plan_i, plan_f, row, little, big):
    """Physical value (DBC units) of signal ``row`` in a frame's 64-bit words."""
    raw = _raw(plan_i, row, little, big)
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


@nb.njit(cache=True)
def decode_signal(plan_i, plan_f, row, data, dlc):
    """Physical value of one signal row in a payload (tests and diagnostics)."""
    little, big = _words(data, dlc)
    return signal_physical(plan_i, plan_f, row, little, big)


@nb.njit(cache=True)
def e2e_code(plan_i, msg, frame_id, data, dlc, counter):
    """The CRC/checksum the message's E2E scheme expects for this payload."""
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
    crc_byte = plan_i[crc_row, S_CRC_BYTE]
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


@nb.njit(cache=True)
def decode_frame(plan_i, plan_f, lookup, frame_id, extended, dlc, data, t, timeouts,
                 latch, msg_state, errors, scratch):
    """Check one frame and, if it passes, write its channels into ``latch``.

    ``timeouts`` float64 [n_msg]: a message silent for longer resynchronises its counter.
    ``scratch`` float64 [N_IN]: room to assemble channel values before committing them, so a
    frame with one out-of-range signal updates none of its channels.
    Returns the message row (>= 0) when accepted, -1 unknown ID, -2 rejected.
    """
    msg = lookup_message(lookup, frame_id, extended)
    n_msg = errors.shape[0] - 1
    if msg < 0:
        errors[n_msg, ERR_UNKNOWN_ID] += 1
        return -1
    if dlc != plan_i[msg, M_DLC]:
        errors[msg, ERR_LENGTH] += 1
        return -2
    little, big = _words(data, dlc)
    counter = np.int64(-1)
    counter_row = plan_i[msg, M_COUNTER_ROW]
    if counter_row >= 0:
        counter = np.int64(_raw(plan_i, counter_row, little, big))
    if plan_i[msg, M_E2E] != E2E_NONE:
        crc_row = plan_i[msg, M_CRC_ROW]
        if e2e_code(plan_i, msg, frame_id, data, dlc, counter) != np.int64(
            _raw(plan_i, crc_row, little, big)
        ):
            errors[msg, ERR_E2E] += 1
            return -2
    if counter_row >= 0:
        last = msg_state[msg, 0]
        fresh = last >= 0.0 and t - msg_state[msg, 1] <= timeouts[msg]
        if fresh:
            modulus = 1 << plan_i[counter_row, S_LENGTH]
            delta = (counter - np.int64(last)) % modulus
            if delta == 0:
                errors[msg, ERR_COUNTER_REPEAT] += 1
                return -2
            if delta > plan_i[msg, M_MAX_DELTA]:
                # Resynchronise on the new value so one lost sequence costs one frame.
                msg_state[msg, 0] = counter
                msg_state[msg, 1] = t
                errors[msg, ERR_COUNTER_JUMP] += 1
                return -2
    first = plan_i[msg, M_SIG_FIRST]
    for row in range(first, first + plan_i[msg, M_SIG_COUNT]):
        slot = plan_i[row, S_SLOT]
        if slot < 0:
            continue
        physical = signal_physical(plan_i, plan_f, row, little, big)
        if plan_i[row, S_CHECK_RANGE] and plan_f[row, F_MIN] < plan_f[row, F_MAX]:
            tolerance = 0.5 * abs(plan_f[row, F_SCALE])
            if not (plan_f[row, F_MIN] - tolerance <= physical <= plan_f[row, F_MAX] + tolerance):
                errors[msg, ERR_RANGE] += 1
                return -2
        if not math.isfinite(physical):
            errors[msg, ERR_RANGE] += 1
            return -2
        if plan_i[row, S_ACCUMULATE]:
            scratch[slot] += physical * plan_f[row, F_FACTOR]
        else:
            scratch[slot] = physical * plan_f[row, F_FACTOR]
    for row in range(first, first + plan_i[msg, M_SIG_COUNT]):
        slot = plan_i[row, S_SLOT]
        if slot >= 0:
            latch[LATCH_VALUE, slot] = scratch[slot]
            latch[LATCH_TIME, slot] = t
            latch[LATCH_SET, slot] = 1.0
    if counter_row >= 0:
        msg_state[msg, 0] = counter
    msg_state[msg, 1] = t
    errors[msg, ERR_ACCEPTED] += 1
    return msg


@nb.njit(cache=True)
def sample_latch(latch, channel_timeouts, t, u):
    """Sample-and-hold of the latch at tick time ``t`` into the input vector ``u``.

    A channel is valid when it has been set and its newest value is at most its timeout old.
    """
    n_in = latch.shape[1]
    for ch in range(n_in):
        age = t - latch[LATCH_TIME, ch]
        valid = latch[LATCH_SET, ch] > 0.5 and age <= channel_timeouts[ch]
        u[ch] = latch[LATCH_VALUE, ch]
        u[n_in + ch] = 1.0 if valid else 0.0
    u[2 * n_in] = t


@nb.njit(cache=True)
def latch_ticks(plan_i, plan_f, lookup, timeouts, channel_timeouts, frame_time, frame_id,
                frame_flags, frame_dlc, frame_data, tick_time, tick_until, latch, msg_state,
                errors, U):
    """The batch engine's front half: decode frames in log order and sample at every tick.

    Frames ``[.., tick_until[k])`` are applied before tick ``k`` is sampled at ``tick_time[k]``
    (the daemon's order: what was received before the tick is latched, then the tick
    samples; from a log's times that is ``searchsorted(frame_time, tick_time, 'right')``, from
    a flight recorder it is the file order). ``frame_flags`` bit 0 = extended ID, bit 1 =
    remote, bit 2 = error frame (the last two are never decoded). Returns frames consumed.
    """
    scratch = np.zeros(latch.shape[1])
    i = 0
    for k in range(tick_time.shape[0]):
        while i < tick_until[k]:
            flags = frame_flags[i]
            if not (flags & 6):
                decode_frame(plan_i, plan_f, lookup, frame_id[i], (flags & 1) != 0,
                             frame_dlc[i], frame_data[i], frame_time[i], timeouts, latch,
                             msg_state, errors, scratch)
            i += 1
        sample_latch(latch, channel_timeouts, tick_time[k], U[k])
    return i


@nb.njit(cache=True)
def _put_raw(little, big, plan_i, row, raw):
    length = plan_i[row, S_LENGTH]
    mask = np.uint64(0xFFFFFFFFFFFFFFFF)
    if length < 64:
        mask = (np.uint64(1) << np.uint64(length)) - np.uint64(1)
    shift = np.uint64(plan_i[row, S_SHIFT])
    raw &= mask
    if plan_i[row, S_BIG_ENDIAN]:
        big = (big & ~(mask << shift)) | (raw << shift)
    else:
        little = (little & ~(mask << shift)) | (raw << shift)
    return little, big


@nb.njit(cache=True)
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


@nb.njit(cache=True)
def encode_frame(plan_i, plan_f, msg, values, counter, out):
    """Encode message row ``msg`` from ``values`` (SI, by slot) into ``out`` (uint8[>= dlc]).

    Values are converted to physical units, clamped to the signal's DBC range and bit width
    (cantools' non-strict encode overflows instead) and rounded to the DBC resolution; signals
    summed into one channel are filled in order, each taking what the previous left over.
    The alive counter and the CRC/checksum are filled last.
    """
    little = np.uint64(0)
    big = np.uint64(0)
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
        raw = _raw_of_physical(plan_i, plan_f, row, physical)
        little, big = _put_raw(little, big, plan_i, row, raw)
        sent = signal_physical(plan_i, plan_f, row, little, big)
        remainder = physical - sent
    counter_row = plan_i[msg, M_COUNTER_ROW]
    if counter_row >= 0:
        little, big = _put_raw(little, big, plan_i, counter_row, np.uint64(counter))
    dlc = plan_i[msg, M_DLC]
    for i in range(dlc):
        byte = (little >> np.uint64(8 * i)) & np.uint64(0xFF)
        byte |= (big >> np.uint64(56 - 8 * i)) & np.uint64(0xFF)
        out[i] = np.uint8(byte)
    if plan_i[msg, M_E2E] != E2E_NONE:
        crc_row = plan_i[msg, M_CRC_ROW]
        code = e2e_code(plan_i, msg, plan_i[msg, M_FRAME_ID], out, dlc, counter)
        little, big = _words(out, dlc)
        little, big = _put_raw(little, big, plan_i, crc_row, np.uint64(code))
        for i in range(dlc):
            byte = (little >> np.uint64(8 * i)) & np.uint64(0xFF)
            byte |= (big >> np.uint64(56 - 8 * i)) & np.uint64(0xFF)
            out[i] = np.uint8(byte)


@nb.njit(cache=True)
def encode_rows(plan_i, plan_f, msg, values, first_counter, out):
    """Encode one frame per row of ``values`` [n, slots] into ``out`` [n, dlc]."""
    counter_row = plan_i[msg, M_COUNTER_ROW]
    modulus = 1 << plan_i[counter_row, S_LENGTH] if counter_row >= 0 else 1
    for k in range(values.shape[0]):
        encode_frame(plan_i, plan_f, msg, values[k], (first_counter + k) % modulus, out[k])
