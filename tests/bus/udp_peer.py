"""Inverter emulator for the two-process udp_multicast test (run as a script, not collected).

Usage: python udp_peer.py PORT N_FRAMES
Sends N_FRAMES INV_Currents (paced), listens for TE_Limits, prints a JSON summary on stdout.
"""

from __future__ import annotations

import asyncio
import json
import sys

from thermal_edge.bus import CanTransport, FrameCodec


async def main(port: int, n_frames: int) -> dict:
    limits = []
    inv = CanTransport(
        {"interface": "udp_multicast", "port": port, "node": "INV", "hop_limit": 7},  # 7 must be overridden to 0
        FrameCodec(),
        on_frame=lambda f: limits.append(f) if f.name == "TE_Limits" else None,
    )
    async with inv:
        import socket

        hops = inv.bus.socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
        for i in range(n_frames):
            inv.send("INV_Currents", dict(INV_Id=i * 0.05, INV_Iq=-i * 0.05, INV_IphRms=i * 0.1))
            await asyncio.sleep(0.001)  # pace: UDP drops frames when a receiver falls behind
        loop = asyncio.get_running_loop()
        end = loop.time() + 60.0  # a hang guard: the limits come every 20 ms
        while len(limits) < 5 and loop.time() < end:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.1)  # let late echoes of our own frames arrive
    return {
        "hop_limit": hops,
        "limits": [f.signals for f in limits],
        "limits_counters": [f.counter for f in limits],
        "transport": inv.stats.as_dict(),
        "codec": inv.codec.stats.as_dict(),
    }


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main(int(sys.argv[1]), int(sys.argv[2])))))
