"""Print the protocol's schema table: every message with its id, class, CAN
identifier, sizes and fields, as text, Markdown (the table embedded in
docs/protocol.md) or JSON."""
from __future__ import annotations

import json

HELP = "print the protocol message table (text, --markdown or --json)"


def add_arguments(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--markdown", action="store_true", help="the generated Markdown of docs/protocol.md")
    g.add_argument("--json", action="store_true", help="machine-readable schema")


def run(args) -> int:
    from coiltrack.protocol.can import BASE_ID, frame_data_lengths
    from coiltrack.protocol.docgen import markdown_table
    from coiltrack.protocol.schema import MESSAGES, PROTOCOL_VERSION, SCHEMA_HASH

    if args.markdown:
        print(markdown_table(), end="")
        return 0
    if args.json:
        doc = {"protocol_version": PROTOCOL_VERSION, "schema_hash": SCHEMA_HASH, "messages": [
            {"id": m.id, "name": m.name, "priority": m.priority, "signable": m.signable,
             "crc_extra": m.crc_extra, "size": m.size, "can_base_id": BASE_ID[m.id],
             "classic_frames": len(frame_data_lengths(m.id)), "doc": m.doc,
             "fields": [{"name": f.name, "type": f.type, "unit": f.unit, "scale": f.scale, "doc": f.doc}
                        for f in m.fields]} for m in MESSAGES]}
        print(json.dumps(doc, indent=2))
        return 0
    print(f"coiltrack protocol v{PROTOCOL_VERSION}, schema hash {SCHEMA_HASH:#010x}")
    for m in MESSAGES:
        flags = " signable" if m.signable else ""
        print(f"{m.id:#04x} {m.name:16s} class {m.priority} CAN {BASE_ID[m.id]:#05x}+node "
              f"{m.size:3d} B {len(frame_data_lengths(m.id)):2d} frames{flags}")
        print("      " + ", ".join(f"{f.name}:{f.type}" + (f"[{f.unit}]" if f.unit else "") for f in m.fields))
    return 0
