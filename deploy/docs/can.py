"""The CAN interface table, from the DBC (cantools)."""
from __future__ import annotations

import re
from pathlib import Path

from .markdown import num, table
from .paths import DBC, shown


def render_can(dbc: Path = DBC) -> str:
    """The DBC as two tables: frames, then signals."""
    import cantools

    db = cantools.database.load_file(str(dbc))
    text = dbc.read_text(encoding="utf-8", errors="replace")
    net = re.search(r'^CM_ "((?:[^"\\]|\\.)*)";', text, re.M | re.S)
    baud = db.dbc.attributes.get("Baudrate") if db.dbc is not None else None
    out = [f"`{shown(dbc)}` (version {db.version or '-'}"
           + (f", {int(baud.value) // 1000} kbit/s" if baud is not None else "") + ")."]
    if net:
        out += ["", " ".join(net.group(1).split())]
    rows = []
    for m in db.messages:
        cycle = f"{m.cycle_time} ms" if m.cycle_time else "event"
        rows.append([f"`{m.name}`", f"0x{m.frame_id:03X} ({m.frame_id})", m.length, cycle,
                     f"{', '.join(m.senders)} → {', '.join(sorted(m.receivers)) or '-'}", m.comment or ""])
    out += ["", *table(["Frame", "ID", "DLC", "Cycle", "From → to", "Content"], rows)]
    rows = []
    for m in db.messages:
        for s in sorted(m.signals, key=lambda s: s.start):
            order = "Intel" if s.byte_order == "little_endian" else "Motorola"
            rng = f"{num(s.minimum)} … {num(s.maximum)}" if s.minimum is not None and s.maximum is not None else ""
            meaning = s.comment or ""
            if s.choices:
                meaning += " Values: " + ", ".join(f"{int(k)} `{v}`" for k, v in sorted(s.choices.items(), key=lambda kv: int(kv[0])))
            rows.append([m.name, f"`{s.name}`", s.start, s.length, f"{order}, {'signed' if s.is_signed else 'unsigned'}",
                         f"{num(s.scale)}, {num(s.offset)}", rng, s.unit or "", meaning.strip()])
    out += ["", *table(["Frame", "Signal", "Start bit", "Bits", "Byte order, sign", "Factor, offset", "Range", "Unit",
                        "Meaning"], rows)]
    return "\n".join(out)
