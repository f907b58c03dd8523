"""End-to-end protection schemes: CRC tables and plain-Python reference implementations.

The numba kernels in :mod:`slipd.codec.kernels` use the same tables; the functions here are
the readable references the tests compare the kernels against.

Schemes (the profile names one per message):

``slipd_crc8``
    slipd.dbc's own: CRC-8/SAE-J1850 as AUTOSAR ``Crc_CalculateCRC8`` computes it
    (polynomial 0x1D, initial value 0xFF, final XOR 0xFF, not reflected) over every payload
    byte except the CRC byte, in order, followed by the low byte of the frame ID; a 4-bit
    alive counter.
``toyota_checksum``
    Toyota's byte sum: ``(dlc + sum of the frame-ID bytes + sum(data[:-1])) & 0xFF`` in the
    last byte (opendbc ``toyota_checksum``).
``autosar_crc8``
    AUTOSAR E2E with CRC8H2F (polynomial 0x2F, init 0xFF, final XOR 0xFF) over the payload
    bytes except the CRC byte, followed by a data-ID byte chosen by the alive counter, as
    Volkswagen MQB uses it (opendbc ``volkswagen_mqb_meb_checksum``).
"""

from __future__ import annotations

import numpy as np


def _crc8_table(poly: int) -> np.ndarray:
    table = np.zeros(256, dtype=np.uint8)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table[byte] = crc
    return table


CRC8_SAE_J1850 = _crc8_table(0x1D)
CRC8_H2F = _crc8_table(0x2F)


def crc8(table: np.ndarray, data: bytes | bytearray, init: int = 0xFF, xor_out: int = 0xFF) -> int:
    crc = init
    for byte in data:
        crc = int(table[crc ^ byte])
    return crc ^ xor_out


def slipd_crc8(frame_id: int, payload: bytes | bytearray, crc_byte: int = 0) -> int:
    """CRC of a slipd.dbc frame: J1850 over the bytes but the CRC byte, then the ID's low byte."""
    covered = bytes(b for i, b in enumerate(payload) if i != crc_byte) + bytes([frame_id & 0xFF])
    return crc8(CRC8_SAE_J1850, covered)


def toyota_checksum(frame_id: int, payload: bytes | bytearray) -> int:
    """Toyota's checksum of a frame (stored in its last byte)."""
    total = len(payload)
    address = frame_id
    while address:
        total += address & 0xFF
        address >>= 8
    total += sum(payload[:-1])
    return total & 0xFF


def autosar_crc8(payload: bytes | bytearray, data_id: int, crc_byte: int = 0) -> int:
    """AUTOSAR CRC8H2F over the bytes but the CRC byte, then the counter's data-ID byte."""
    covered = bytes(b for i, b in enumerate(payload) if i != crc_byte) + bytes([data_id])
    return crc8(CRC8_H2F, covered)
