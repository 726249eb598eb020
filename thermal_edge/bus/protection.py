"""End-to-end protection of one received or sent frame: alive counter, CRC, or none.

The frames of this project's CAN matrix carry both: a 4-bit counter ``<frame>_Counter`` and a
CRC-8/SAE-J1850 ``<frame>_CRC`` over the data ID ``0x1000 + identifier`` (:meth:`FrameProtection.matrix`).
An inverter with its own matrix declares per frame what it has (``codec.protection`` in
``edge.yaml``); :class:`~thermal_edge.bus.codec.FrameCodec` checks what is declared and nothing
else.

What a receiver cannot detect without each part (the stale check -- a frame missing for longer
than its timeout -- still catches a sender that stops):

- without an **alive counter**: a sender whose software hangs while its CAN controller keeps
  resending the last buffer (frozen values look fresh: only the stuck-sensor check, over minutes,
  can notice a temperature that no longer moves), a repeated or replayed frame, and frames lost
  on the way (never counted);
- without a **CRC**: a payload corrupted after the CAN controller's own CRC-15 (in a gateway, a
  driver or a buffer) or beyond what that CRC detects, and a frame of another sender that happens
  to use the identifier: each is taken as a valid reading.
"""

from __future__ import annotations

from dataclasses import dataclass

from .crc import CRC8_ALGORITHMS, data_id
from .frames import COUNTER_SUFFIX, CRC_SUFFIX

__all__ = ["MATRIX_CRC_ALGORITHM", "FrameProtection"]

#: The CRC of this project's CAN matrix.
MATRIX_CRC_ALGORITHM = "crc8_sae_j1850"


@dataclass(frozen=True)
class FrameProtection:
    """What protects one frame end to end (all None: nothing).

    Attributes
    ----------
    counter : str or None
        Name of the alive-counter signal (its width is the signal's length in the DBC; it counts
        +1 modulo 2**width per transmission).
    crc : str or None
        Name of the CRC signal (8 bits, one whole payload byte).
    crc_algorithm : str
        One of :data:`~thermal_edge.bus.crc.CRC8_ALGORITHMS`.
    data_id : int or None
        16-bit data ID the CRC starts with (low byte, then high byte); None: the CRC covers the
        payload only.
    """

    counter: str | None = None
    crc: str | None = None
    crc_algorithm: str = MATRIX_CRC_ALGORITHM
    data_id: int | None = None

    def __post_init__(self) -> None:
        if self.crc_algorithm not in CRC8_ALGORITHMS:
            raise ValueError(f"unknown CRC algorithm {self.crc_algorithm!r} (known: {', '.join(CRC8_ALGORITHMS)})")
        if self.data_id is not None and not 0 <= self.data_id <= 0xFFFF:
            raise ValueError(f"data ID {self.data_id} is not a 16-bit value")

    @classmethod
    def matrix(cls, frame_name: str, frame_id: int) -> FrameProtection:
        """The protection of a frame of this project's CAN matrix."""
        return cls(frame_name + COUNTER_SUFFIX, frame_name + CRC_SUFFIX, MATRIX_CRC_ALGORITHM, data_id(frame_id))

    @property
    def none(self) -> bool:
        """Neither counter nor CRC."""
        return self.counter is None and self.crc is None

    def unseen(self) -> list[str]:
        """What a receiver cannot detect on a frame with this protection (empty: nothing more than
        the CAN matrix's frames)."""
        out = []
        if self.counter is None:
            out.append("a frozen or repeating sender, lost frames (no alive counter)")
        if self.crc is None:
            out.append("a corrupted payload that passed the CAN controller (no CRC)")
        return out

    def describe(self) -> str:
        """One line for messages: ``counter X, CRC crc8_... over data ID 0x10A0`` or ``none``."""
        parts = []
        if self.counter:
            parts.append(f"counter {self.counter}")
        if self.crc:
            over = f" over data ID 0x{self.data_id:04X}" if self.data_id is not None else ""
            parts.append(f"CRC {self.crc} ({self.crc_algorithm}{over})")
        return ", ".join(parts) or "none"
