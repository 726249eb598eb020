"""The fault bench's own side of the bus, built from the CAN matrix alone (``dbc/thermal_edge.dbc``
through cantools, its own CRC-8/SAE-J1850, raw multicast sockets on the loopback interface and
msgpack in python-can's ``udp_multicast`` datagram layout), so that what it measures does not rest on the project's codec
or transport.

Run as a module it is one of two helper processes of the bench:

- ``monitor``: joins the bus group and writes every ``TE_Limits`` it receives, stamped with the
  kernel's receive time (``SO_TIMESTAMPNS``), as one text line to a file; being a process of its
  own, the bench's other work cannot delay it, and the kernel stamp does not depend on when it reads;
- ``flood``: sends frames at a fixed rate (valid inverter frames with their counters, or one kind of
  bad frame) and prints how many it sent per frame name as JSON.
"""
from __future__ import annotations

import argparse
import json
import socket
import struct
import sys
import time
from functools import lru_cache
from pathlib import Path
from typing import Any

import cantools
import msgpack

from thermal_edge.bus.frames import DEFAULT_DBC_PATH

#: the CAN matrix the service ships with (the contract both sides are built from)
DBC = DEFAULT_DBC_PATH
TE_LIMITS_ID = 0x2A0
INPUT_FRAMES = ("INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps")
_SO_TIMESTAMPNS = 35  # Linux (asm-generic/socket.h); not exported by the socket module


@lru_cache(maxsize=1)
def dbc() -> Any:
    """The CAN matrix (cantools database)."""
    return cantools.database.load_file(str(DBC))


def crc8_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850: polynomial 0x1D, initial value 0xFF, final XOR 0xFF, not reflected.

    >>> hex(crc8_j1850(b"123456789"))  # the check value the CAN matrix gives
    '0x4b'
    """
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def crc8(can_id: int, payload7: bytes) -> int:
    """A frame's CRC byte: over the data ID 0x1000 + ``can_id`` (low byte, then high byte) and
    payload bytes 0-6, as the CAN matrix specifies."""
    data_id = 0x1000 + can_id
    return crc8_j1850(bytes((data_id & 0xFF, data_id >> 8)) + bytes(payload7))


def encode(name: str, signals: dict[str, float], counter: int) -> bytes:
    """A frame of the matrix with its alive counter (mod 16) and a valid CRC in byte 7."""
    msg = dbc().get_message_by_name(name)
    sig = {**signals, f"{name}_Counter": counter % 16, f"{name}_CRC": 0}
    data = bytearray(msg.encode(sig, strict=False))
    data[7] = crc8(msg.frame_id, bytes(data[:7]))
    return bytes(data)


def frame_id(name: str) -> int:
    return int(dbc().get_message_by_name(name).frame_id)


def datagram(arbitration_id: int, data: bytes, *, extended: bool = False, remote: bool = False, error: bool = False,
             fd: bool = False, dlc: int | None = None, timestamp: float | None = None) -> bytes:
    """One datagram in python-can's ``udp_multicast`` layout (a msgpack map of the message fields)."""
    return msgpack.packb({
        "timestamp": time.time() if timestamp is None else timestamp, "arbitration_id": arbitration_id,
        "is_extended_id": extended, "is_remote_frame": remote, "is_error_frame": error, "channel": None,
        "dlc": len(data) if dlc is None else dlc, "data": bytes(data), "is_fd": fd, "bitrate_switch": False,
        "error_state_indicator": False,
    }, use_bin_type=True)


def sender_socket(group: str) -> socket.socket:
    """A UDP socket sending to the group on this host only: hop limit 0, loopback copies on, sent
    on the loopback interface (where the service joins its group)."""
    if ":" in group:
        s = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, 0)
        s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)
    else:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    return s


def receiver_socket(group: str, port: int) -> socket.socket:
    """A UDP socket bound to the group and joined to it on the loopback interface, with kernel
    receive stamps and a receive buffer of several seconds of a full bus."""
    family = socket.AF_INET6 if ":" in group else socket.AF_INET
    s = socket.socket(family, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
    s.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
    s.bind((group, port))
    if family == socket.AF_INET6:
        mreq = socket.inet_pton(socket.AF_INET6, group) + struct.pack("@I", 0)
        s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, mreq)
    else:
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton("127.0.0.1"))
    return s


def monitor(group: str, port: int, out: Path) -> None:
    """Write ``t current_a torque_nm reason active counter crc_ok`` for every ``TE_Limits`` (t: kernel
    receive time, s since the epoch) until killed."""
    sock = receiver_socket(group, port)
    msg = dbc().get_message_by_frame_id(TE_LIMITS_ID)
    with open(out, "w", buffering=1) as fh:
        fh.write("ready\n")
        while True:
            data, anc, _, _ = sock.recvmsg(65536, 1024)
            t = time.time()
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                    sec, ns = struct.unpack("@qq", cdata[:16])
                    t = sec + ns * 1e-9
            try:
                d = msgpack.unpackb(data, raw=False)
                if d.get("arbitration_id") != TE_LIMITS_ID or d.get("is_extended_id"):
                    continue
                payload = bytes(d["data"])
                s = msg.decode(payload, decode_choices=False, scaling=True)
            except Exception:  # a bad datagram of the bench's own making, or a short TE_Limits
                continue
            ok = int(len(payload) == 8 and crc8(TE_LIMITS_ID, payload[:7]) == payload[7])
            fh.write(f"{t:.6f} {s['TE_CurrentLimit']:.3f} {s['TE_TorqueLimit']:.2f} {int(s['TE_DerateReason'])} "
                     f"{int(s['TE_DerateActive'])} {int(s['TE_Limits_Counter'])} {ok}\n")


# ----------------------------------------------------------------------------------------------
def idle_signals(temps_c: float = 25.0) -> dict[str, dict[str, float]]:
    """Signals of a machine at standstill, no current, every temperature at ``temps_c`` and valid."""
    return {
        "INV_Currents": {"INV_Id": 0.0, "INV_Iq": 0.0, "INV_IphRms": 0.0},
        "INV_Mechanics": {"INV_Speed": 0.0, "INV_Torque": 0.0, "INV_Udc": 560.0},
        "INV_StatorTemps": {"INV_T_WindingSlot": temps_c, "INV_T_EndWinding": temps_c, "INV_T_Housing": temps_c,
                            "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0, "INV_S_Housing": 0},
        "INV_AmbientTemps": {"INV_T_Ambient": temps_c, "INV_T_Coolant": 359.5, "INV_S_Ambient": 0, "INV_S_Coolant": 3},
    }


def bad_frame(kind: str, k: int) -> bytes:
    """The ``k``-th datagram of one kind of bad frame (the kinds of :data:`BAD_KINDS`)."""
    cur = encode("INV_Currents", idle_signals()["INV_Currents"], k)
    cid = frame_id("INV_Currents")
    if kind == "bad_crc":
        return datagram(cid, cur[:7] + bytes([cur[7] ^ 0x5A]))
    if kind == "short_dlc":
        return datagram(cid, cur[:4])
    if kind == "zero_dlc":
        return datagram(frame_id("INV_StatorTemps"), b"")
    if kind == "unknown_id":
        return datagram(0x123, bytes(8))
    if kind == "extended_id":
        return datagram(0x18FF00A0, cur, extended=True)
    if kind == "remote_frame":
        return datagram(frame_id("INV_StatorTemps"), b"", remote=True, dlc=8)
    if kind == "error_frame":
        return datagram(0x20000080, bytes(8), error=True, extended=True)
    if kind == "can_fd":
        return datagram(cid, cur + bytes(8), fd=True)
    if kind == "garbage_known_id":
        return datagram(frame_id("INV_StatorTemps"), b"\xff" * 8)
    if kind == "te_id_spoof":  # a frame on an identifier the service itself sends (not TE_Limits)
        return datagram(frame_id("TE_Status"), bytes(8))
    if kind == "not_msgpack":
        return b"\xc1not a msgpack datagram"
    if kind == "classic_12_bytes":
        return datagram(cid, bytes(12))
    if kind == "std_id_0x800":
        return datagram(0x800, bytes(8))
    if kind == "remote_with_data":
        return datagram(cid, cur, remote=True)
    if kind == "empty_datagram":
        return b""
    if kind == "msgpack_list":
        return msgpack.packb([1, 2, 3])
    if kind == "msgpack_missing_fields":
        return msgpack.packb({"arbitration_id": cid})
    if kind == "huge_datagram":
        return datagram(cid, bytes(8)) + bytes(60000)
    raise ValueError(f"unknown bad frame kind {kind!r}")


#: every kind of bad frame; those python-can cannot unpack are the UNDECODABLE ones
BAD_KINDS = ("bad_crc", "short_dlc", "zero_dlc", "unknown_id", "extended_id", "remote_frame", "error_frame", "can_fd",
             "garbage_known_id", "te_id_spoof", "not_msgpack", "classic_12_bytes", "std_id_0x800", "remote_with_data",
             "empty_datagram", "msgpack_list", "msgpack_missing_fields", "huge_datagram")
UNDECODABLE = frozenset({"not_msgpack", "classic_12_bytes", "std_id_0x800", "remote_with_data", "empty_datagram",
                         "msgpack_list", "msgpack_missing_fields", "huge_datagram"})


def flood(group: str, port: int, kind: str, rate: float, seconds: float) -> dict[str, Any]:
    """Send ``rate`` frames/s for ``seconds``: ``valid`` sends the four inverter frames in the DBC's
    10:1 mix (10 ms / 100 ms) with running counters, any other kind that bad frame."""
    sock = sender_socket(group)
    idle = idle_signals()
    valid = {n: [encode(n, idle[n], k) for k in range(16)] for n in INPUT_FRAMES}
    pattern = ["INV_Currents", "INV_Mechanics"] * 10 + ["INV_StatorTemps", "INV_AmbientTemps"]
    bad = [bad_frame(kind, k) for k in range(16)] if kind != "valid" else []
    ids = {n: frame_id(n) for n in INPUT_FRAMES}
    counters = dict.fromkeys(INPUT_FRAMES, 0)
    sent = dict.fromkeys(INPUT_FRAMES, 0) if kind == "valid" else {kind: 0}
    n = 0
    failures = 0
    t0 = time.monotonic()
    while True:
        now = time.monotonic() - t0
        if now >= seconds:
            break
        due = int(min(now + 0.001, seconds) * rate)
        while n < due:
            if kind == "valid":
                name = pattern[n % len(pattern)]
                k = counters[name]
                counters[name] = (k + 1) % 16
                payload = datagram(ids[name], valid[name][k])
            else:
                name = kind
                payload = bad[n % 16]
            try:
                sock.sendto(payload, (group, port))
                sent[name] += 1
            except OSError:
                failures += 1
            n += 1
        time.sleep(max(0.0, 0.001 - ((time.monotonic() - t0) - now)))
    return {"sent": sent, "seconds": time.monotonic() - t0, "send_failures": failures}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.faults.wire")
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("monitor")
    m.add_argument("--group", required=True)
    m.add_argument("--port", type=int, required=True)
    m.add_argument("--out", required=True)
    f = sub.add_parser("flood")
    f.add_argument("--group", required=True)
    f.add_argument("--port", type=int, required=True)
    f.add_argument("--kind", required=True, choices=("valid",) + BAD_KINDS)
    f.add_argument("--rate", type=float, required=True)
    f.add_argument("--seconds", type=float, required=True)
    a = ap.parse_args(argv)
    if a.cmd == "monitor":
        monitor(a.group, a.port, Path(a.out))
    else:
        print(json.dumps(flood(a.group, a.port, a.kind, a.rate, a.seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
