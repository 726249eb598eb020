"""Receive-path benchmark of CanTransport on udp_multicast (a script, not collected by pytest).

Usage: python tests/bus/bench_rx.py [RATE_FPS] [SECONDS] [--profile]

A sender process puts INV_Currents and INV_Mechanics (half each, valid counters and CRCs) on
the bus at RATE frames/s, paced in 1 ms slices; this process receives them through a
CanTransport and prints one JSON line: frames sent, received, lost by the codec's count, the
receiver's CPU seconds and CPU s per 10,000 frames. ``--profile`` prints the top functions of
a cProfile of the receiving process as well.
"""

from __future__ import annotations

import asyncio
import cProfile
import json
import os
import pstats
import socket
import subprocess
import sys
import time

from thermal_edge.bus import CanTransport, FrameCodec, create_bus

SENDER = r"""
import sys, time
from thermal_edge.bus import FrameCodec, create_bus
import can
port, rate, seconds = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
codec = FrameCodec()
bus = create_bus({"interface": "udp_multicast", "port": port, "node": "INV"})
n = int(rate * seconds)
names = ("INV_Currents", "INV_Mechanics")
values = ({"INV_Id": 1.0, "INV_Iq": 2.0, "INV_IphRms": 3.0}, {"INV_Speed": 1000.0, "INV_Torque": 10.0, "INV_Udc": 600.0})
msgs = []
for i in range(n):
    k = i % 2
    msgs.append(can.Message(arbitration_id=codec.frame_id(names[k]), data=codec.encode(names[k], values[k]), is_extended_id=False))
time.sleep(0.5)
t0 = time.monotonic()
for i, msg in enumerate(msgs):
    due = t0 + i / rate
    while time.monotonic() < due - 0.001:
        time.sleep(0.0005)
    msg.timestamp = time.time()
    bus.send(msg)
bus.shutdown()
print(n)
"""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def main(rate: float, seconds: float, profile: bool) -> dict:
    port = free_port()
    count = 0

    def on_frame(frame) -> None:
        nonlocal count
        count += 1

    tr = CanTransport({"interface": "udp_multicast", "port": port, "node": "TE"}, FrameCodec(), on_frame=on_frame)
    prof = cProfile.Profile() if profile else None
    async with tr:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", SENDER, str(port), str(rate), str(seconds), stdout=asyncio.subprocess.PIPE,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        cpu0 = time.process_time()
        if prof:
            prof.enable()
        out, _ = await proc.communicate()
        await asyncio.sleep(0.3)
        if prof:
            prof.disable()
        cpu = time.process_time() - cpu0
    sent = int(out.decode().split()[-1])
    st = tr.codec.stats
    if prof:
        pstats.Stats(prof, stream=sys.stderr).sort_stats("tottime").print_stats(15)
    return {"rate_fps": rate, "seconds": seconds, "sent": sent, "received": count, "lost_counted": st.lost,
            "missing": sent - count, "cpu_s": round(cpu, 2),
            "cpu_s_per_10k": round(cpu / max(count, 1) * 10_000, 3),
            "rx_fps": round(count / seconds)}


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    result = asyncio.run(main(float(args[0]) if args else 8000.0, float(args[1]) if len(args) > 1 else 10.0,
                              "--profile" in sys.argv))
    print(json.dumps(result))
