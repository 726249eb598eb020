"""CRC-8/SAE-J1850 and the frame protection CRC of the thermal_edge CAN matrix; the CRC-8
algorithms an inverter's own frames may use.

The CRC of every frame of the matrix (byte 7) is CRC-8/SAE-J1850 -- polynomial 0x1D, initial
value 0xFF, final XOR 0xFF, no reflection -- computed over the data ID's low
byte, then its high byte, then payload bytes 0-6. The data ID is
``0x1000 + CAN identifier``. The check value over ``b"123456789"`` is 0x4B.

A frame of another matrix declares its CRC (:class:`~thermal_edge.bus.protection.FrameProtection`):
one of :data:`CRC8_ALGORITHMS` (named as in the CRC catalogue), over the data ID's low byte then
its high byte (if it has one), then every payload byte but the CRC's own, in order
(:func:`protection_crc_function`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from dataclasses import dataclass

__all__ = [
    "CRC8_ALGORITHMS",
    "CRC8_SAE_J1850_CHECK",
    "CRC8_SAE_J1850_INIT",
    "CRC8_SAE_J1850_POLY",
    "CRC8_SAE_J1850_XOROUT",
    "DATA_ID_BASE",
    "Crc8Algorithm",
    "crc8",
    "crc8_sae_j1850",
    "data_id",
    "frame_crc",
    "frame_crc_function",
    "protection_crc_function",
]

#: Generator polynomial x^8 + x^4 + x^3 + x^2 + 1 (normal form, top bit implicit).
CRC8_SAE_J1850_POLY = 0x1D
#: Initial register value.
CRC8_SAE_J1850_INIT = 0xFF
#: Value XORed onto the register at the end.
CRC8_SAE_J1850_XOROUT = 0xFF
#: CRC of the ASCII bytes ``"123456789"`` (the catalogue check value).
CRC8_SAE_J1850_CHECK = 0x4B
#: Data ID of a frame = DATA_ID_BASE + CAN identifier.
DATA_ID_BASE = 0x1000


def _make_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        reg = byte
        for _ in range(8):
            reg = ((reg << 1) ^ poly) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
        table.append(reg)
    return tuple(table)


_TABLE: tuple[int, ...] = _make_table(CRC8_SAE_J1850_POLY)


def crc8_sae_j1850(data: bytes | bytearray | memoryview | Iterable[int]) -> int:
    """CRC-8/SAE-J1850 of a byte sequence (table driven).

    Parameters
    ----------
    data : bytes-like or iterable of int
        The bytes to protect, each 0..255.

    Returns
    -------
    int
        The CRC, 0..255 (initial value and final XOR 0xFF already applied).
    """
    reg = CRC8_SAE_J1850_INIT
    table = _TABLE
    for byte in bytes(data):
        reg = table[reg ^ byte]
    return reg ^ CRC8_SAE_J1850_XOROUT


def data_id(can_id: int) -> int:
    """Data ID of a frame, the value the CRC is seeded with.

    Parameters
    ----------
    can_id : int
        11-bit CAN identifier (0..0x7FF).

    Returns
    -------
    int
        ``0x1000 + can_id`` (16 bits).
    """
    if not 0 <= can_id <= 0x7FF:
        raise ValueError(f"CAN identifier 0x{can_id:X} is not an 11-bit identifier")
    return DATA_ID_BASE + can_id


def frame_crc_function(can_id: int) -> Callable[[bytes | bytearray], int]:
    """The frame CRC of one identifier as a function of the payload, the data ID pre-computed.

    Parameters
    ----------
    can_id : int
        11-bit CAN identifier of the frame.

    Returns
    -------
    callable(bytes) -> int
        ``f(payload)`` equals :func:`frame_crc` ``(can_id, payload)`` for a payload of at least
        7 bytes (not checked: the receive path calls it once per frame after its length check).
    """
    did = data_id(can_id)
    t = _TABLE
    seed = t[t[CRC8_SAE_J1850_INIT ^ (did & 0xFF)] ^ (did >> 8)]
    xorout = CRC8_SAE_J1850_XOROUT

    def crc(p: bytes | bytearray) -> int:
        return t[t[t[t[t[t[t[seed ^ p[0]] ^ p[1]] ^ p[2]] ^ p[3]] ^ p[4]] ^ p[5]] ^ p[6]] ^ xorout

    return crc


def frame_crc(can_id: int, payload: bytes | bytearray | memoryview) -> int:
    """Protection CRC of a frame (the value that belongs in byte 7).

    Parameters
    ----------
    can_id : int
        11-bit CAN identifier of the frame.
    payload : bytes-like
        The frame data; bytes 0-6 are protected (byte 7 and beyond are ignored).
        Must hold at least 7 bytes.

    Returns
    -------
    int
        CRC-8/SAE-J1850 over data-ID low byte, data-ID high byte, payload[0:7].
    """
    payload = bytes(payload)
    if len(payload) < 7:
        raise ValueError(f"payload has {len(payload)} bytes, at least 7 are protected")
    did = data_id(can_id)
    return crc8_sae_j1850(bytes((did & 0xFF, did >> 8)) + payload[:7])


@dataclass(frozen=True)
class Crc8Algorithm:
    """A non-reflected CRC-8 of the CRC catalogue (polynomial in normal form, top bit implicit).

    Attributes
    ----------
    poly, init, xorout : int
        Polynomial, initial register value, final XOR.
    check : int
        The CRC of the ASCII bytes ``"123456789"`` (the catalogue's check value).
    """

    poly: int
    init: int
    xorout: int
    check: int


#: The CRC-8 algorithms a frame may declare, by the name edge.yaml gives (``crc_algorithm``).
CRC8_ALGORITHMS: dict[str, Crc8Algorithm] = {
    "crc8_sae_j1850": Crc8Algorithm(0x1D, 0xFF, 0xFF, 0x4B),  # this CAN matrix's; AUTOSAR's CRC8
    "crc8_autosar": Crc8Algorithm(0x2F, 0xFF, 0xFF, 0xDF),  # AUTOSAR's CRC8H2F
    "crc8_gsm_a": Crc8Algorithm(0x1D, 0x00, 0x00, 0x37),  # SAE J1850's polynomial, zero init and XOR
    "crc8_smbus": Crc8Algorithm(0x07, 0x00, 0x00, 0xF4),
}


@functools.cache
def _table_of(poly: int) -> tuple[int, ...]:
    return _make_table(poly)


def crc8(algorithm: str, data: bytes | bytearray | memoryview | Iterable[int]) -> int:
    """CRC-8 of a byte sequence with one of :data:`CRC8_ALGORITHMS`.

    Parameters
    ----------
    algorithm : str
        A key of :data:`CRC8_ALGORITHMS`.
    data : bytes-like or iterable of int
        The bytes to protect, each 0..255.

    Returns
    -------
    int
        The CRC, 0..255.
    """
    alg = CRC8_ALGORITHMS[algorithm]
    table = _table_of(alg.poly)
    reg = alg.init
    for byte in bytes(data):
        reg = table[reg ^ byte]
    return reg ^ alg.xorout


def protection_crc_function(algorithm: str, data_id_value: int | None, crc_byte: int) -> Callable[[bytes | bytearray], int]:
    """The CRC of a frame as a function of its payload: over the data ID's low byte then its high
    byte (none without a data ID), then every payload byte but ``crc_byte``, in order.

    Parameters
    ----------
    algorithm : str
        A key of :data:`CRC8_ALGORITHMS`.
    data_id_value : int or None
        The frame's 16-bit data ID, None for none.
    crc_byte : int
        Index of the payload byte that holds the CRC.

    Returns
    -------
    callable(bytes) -> int
    """
    alg = CRC8_ALGORITHMS[algorithm]
    table = _table_of(alg.poly)
    seed = alg.init
    if data_id_value is not None:
        seed = table[table[seed ^ (data_id_value & 0xFF)] ^ ((data_id_value >> 8) & 0xFF)]
    xorout = alg.xorout

    def crc(p: bytes | bytearray) -> int:
        reg = seed
        for i, byte in enumerate(p):
            if i != crc_byte:
                reg = table[reg ^ byte]
        return reg ^ xorout

    return crc
