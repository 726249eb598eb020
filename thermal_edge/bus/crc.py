"""CRC-8/SAE-J1850 and the frame protection CRC of the thermal_edge CAN matrix.

The CRC of every frame (byte 7) is CRC-8/SAE-J1850 -- polynomial 0x1D, initial
value 0xFF, final XOR 0xFF, no reflection -- computed over the data ID's low
byte, then its high byte, then payload bytes 0-6. The data ID is
``0x1000 + CAN identifier``. The check value over ``b"123456789"`` is 0x4B.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

__all__ = [
    "CRC8_SAE_J1850_CHECK",
    "CRC8_SAE_J1850_INIT",
    "CRC8_SAE_J1850_POLY",
    "CRC8_SAE_J1850_XOROUT",
    "DATA_ID_BASE",
    "crc8_sae_j1850",
    "data_id",
    "frame_crc",
    "frame_crc_function",
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
