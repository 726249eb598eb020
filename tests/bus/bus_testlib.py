"""Helpers shared by the CAN layer tests (a uniquely named module: importable from any test folder layout)."""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path

from own_ports import own_udp_port

REPO = Path(__file__).resolve().parents[2]
DBC_PATH = REPO / "dbc" / "thermal_edge.dbc"
MATRIX_PATH = Path(os.environ.get("THERMAL_EDGE_CAN_MATRIX", "/work/shared/reference/can-matrix.md"))


@dataclass(frozen=True)
class MatrixSignal:
    frame_id: int
    frame: str
    sender: str
    cycle_ms: int
    name: str
    start: int
    bits: int
    signed: bool
    factor: float
    offset: float
    unit: str


def parse_can_matrix(text: str) -> list[MatrixSignal]:
    """Parse the frame tables of can-matrix.md (independent of the DBC)."""
    rows: list[MatrixSignal] = []
    sender = None
    frame_id = frame = cycle = None
    for line in text.splitlines():
        heading = re.match(r"^##\s+(.*)$", line)
        if heading:
            title = heading.group(1).lower()
            if title.startswith("inverter"):
                sender = "INV"
            elif title.startswith("thermal_edge"):
                sender = "TE"
            else:
                sender = None
            continue
        if sender is None or not line.startswith("|"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 10 or cells[0] == "ID" or set(cells[0]) <= {"-", ":"} and cells[0]:
            continue
        if cells[0]:
            frame_id, frame = int(cells[0], 16), cells[1]
            cycle = int(re.match(r"(\d+)\s*ms", cells[2]).group(1))
        minus = lambda s: s.replace("\u2212", "-")  # noqa: E731  (the matrix uses U+2212)
        rows.append(
            MatrixSignal(
                frame_id=frame_id,
                frame=frame,
                sender=sender,
                cycle_ms=cycle,
                name=cells[3],
                start=int(cells[4]),
                bits=int(cells[5]),
                signed={"yes": True, "no": False}[cells[6]],
                factor=float(minus(cells[7])),
                offset=float(minus(cells[8])),
                unit=cells[9],
            )
        )
    return rows


def free_udp_port() -> int:
    """A UDP port for this test's ``udp_multicast`` buses, no other process's while this one runs."""
    return own_udp_port()


def crc8_bitwise(data: bytes) -> int:
    """Textbook MSB-first CRC-8/SAE-J1850: poly 0x1D, init 0xFF, xorout 0xFF, no reflection."""
    reg = 0xFF
    for byte in data:
        reg ^= byte
        for _ in range(8):
            reg = ((reg << 1) ^ 0x1D) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
    return reg ^ 0xFF


def udp_socket_drops(sock: socket.socket) -> int:
    """Datagrams the kernel dropped for this UDP socket so far (a full receive queue), from
    ``/proc/net/udp``'s per-socket ``drops`` column: an exact count of what never reached the reader."""
    inode = os.fstat(sock.fileno()).st_ino
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[9]) == inode:
            return int(fields[-1])
    raise LookupError(f"socket inode {inode} not in /proc/net/udp")
