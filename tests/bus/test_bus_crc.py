"""CRC-8/SAE-J1850 and the frame CRC, against a bit-by-bit reference."""

from __future__ import annotations

import random

import pytest
from bus_testlib import crc8_bitwise

from thermal_edge.bus.crc import crc8_sae_j1850, data_id, frame_crc


def crc8_polydiv(data: bytes) -> int:
    """Same CRC as GF(2) polynomial division: (M(x) with init XORed in) * x^8 mod 0x11D, then xorout."""
    if not data:
        return 0xFF ^ 0xFF  # nothing to divide: init, then xorout
    msg = bytearray(data)
    msg[0] ^= 0xFF
    m = int.from_bytes(bytes(msg), "big") << 8
    while m.bit_length() > 8:
        m ^= 0x11D << (m.bit_length() - 9)
    return m ^ 0xFF


def test_check_value():
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_bitwise(b"123456789") == 0x4B
    assert crc8_polydiv(b"123456789") == 0x4B


def test_table_matches_bitwise_reference():
    rng = random.Random(7)
    for n in range(0, 40):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert crc8_sae_j1850(data) == crc8_bitwise(data) == crc8_polydiv(data)
    assert crc8_sae_j1850(b"") == 0x00  # init 0xFF xor 0xFF


def test_data_id():
    assert data_id(0x0A0) == 0x10A0
    assert data_id(0x2C0) == 0x12C0
    with pytest.raises(ValueError):
        data_id(0x800)


def test_hand_computed_frame():
    # INV_Currents: Id = 10 A -> raw 200 = 0x00C8; Iq = -5 A -> raw -100 = 0xFF9C;
    # IphRms = 8 A -> raw 160 = 0x00A0; counter 3 in byte 6 (bit 48).
    payload = bytes([0xC8, 0x00, 0x9C, 0xFF, 0xA0, 0x00, 0x03])
    # CRC input: data ID 0x10A0 low byte, high byte, then payload bytes 0-6.
    expected = crc8_bitwise(bytes([0xA0, 0x10]) + payload)
    assert expected == crc8_polydiv(bytes([0xA0, 0x10]) + payload)
    assert frame_crc(0x0A0, payload + b"\x00") == expected
    assert frame_crc(0x0A0, payload + b"\xAB") == expected  # byte 7 is not protected
    assert expected == 0xFA  # pinned: bitwise and polynomial-division references agree on it


def test_frame_crc_depends_on_identifier():
    payload = bytes(8)
    assert frame_crc(0x0A0, payload) != frame_crc(0x0A1, payload)
    with pytest.raises(ValueError):
        frame_crc(0x0A0, b"\x00" * 6)
