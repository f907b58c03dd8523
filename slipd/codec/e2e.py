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
``honda_checksum``
    Honda's 4-bit checksum: 8 minus the sum of the frame ID's nibbles and of every payload
    nibble except the checksum nibble (the last byte's low nibble), + 3 for an extended ID,
    modulo 16; a 2-bit counter (opendbc ``honda_checksum``).
``hkg_canfd_crc16``
    Hyundai/Kia CAN FD: CRC-16/XMODEM (polynomial 0x1021, init 0) over the payload from
    byte 2, then the frame ID's low and high byte, XOR a constant per frame length; the CRC
    in bytes 0-1, an 8-bit counter (opendbc ``hkg_can_fd_checksum``).
``subaru_checksum``
    Subaru global platform: the sum of the frame-ID bytes and of payload bytes 1.., & 0xFF,
    in byte 0 (opendbc ``subaru_checksum``).
``tesla_checksum``
    Tesla Model 3/Y party bus: ID low byte + ID high byte + every payload byte but the
    checksum byte, & 0xFF (opendbc ``tesla_checksum``).

Each is checked bit-exact against opendbc's own function on random payloads
(tests/test_e2e_opendbc.py).
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


def _crc16_table(poly: int) -> np.ndarray:
    table = np.zeros(256, dtype=np.int64)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table[byte] = crc
    return table


CRC8_SAE_J1850 = _crc8_table(0x1D)
CRC8_H2F = _crc8_table(0x2F)
CRC16_XMODEM = _crc16_table(0x1021)
#: Final XOR of the Hyundai/Kia CAN FD CRC by frame length (opendbc: 8, 16, 24, 32 bytes;
#: other lengths are not XORed).
HKG_CANFD_XOR = np.zeros(65, dtype=np.int64)
HKG_CANFD_XOR[[8, 16, 24, 32]] = [0x5F29, 0x041D, 0x819D, 0x9F5B]


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


def honda_checksum(frame_id: int, payload: bytes | bytearray) -> int:
    """Honda's 4-bit checksum of a frame (stored in the last byte's low nibble)."""
    total = 0
    address = frame_id
    while address:
        total += address & 0xF
        address >>= 4
    for i, byte in enumerate(payload):
        x = byte >> 4 if i == len(payload) - 1 else byte
        total += (x & 0xF) + (x >> 4)
    total = 8 - total
    if frame_id > 0x7FF:
        total += 3
    return total & 0xF


def hkg_canfd_crc16(frame_id: int, payload: bytes | bytearray) -> int:
    """Hyundai/Kia CAN FD CRC-16 of a frame (stored little-endian in bytes 0-1)."""
    crc = 0
    for byte in bytes(payload[2:]) + bytes([frame_id & 0xFF, (frame_id >> 8) & 0xFF]):
        crc = ((crc << 8) ^ int(CRC16_XMODEM[(crc >> 8) ^ byte])) & 0xFFFF
    return crc ^ int(HKG_CANFD_XOR[len(payload)])


def subaru_checksum(frame_id: int, payload: bytes | bytearray) -> int:
    total = 0
    address = frame_id
    while address:
        total += address & 0xFF
        address >>= 8
    return (total + sum(payload[1:])) & 0xFF


def tesla_checksum(frame_id: int, payload: bytes | bytearray, crc_byte: int) -> int:
    covered = sum(b for i, b in enumerate(payload) if i != crc_byte)
    return ((frame_id & 0xFF) + ((frame_id >> 8) & 0xFF) + covered) & 0xFF
