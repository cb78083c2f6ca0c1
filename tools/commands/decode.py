"""Decode a capture into readable messages, one line each: a raw serial
capture (COBS frames) or a python-can log (.log, .asc, .blf, .trc, .csv,
.mf4, .db), with the counters of bad frames at the end. A capture damaged
further on (cut short, a line not UTF-8, a log python-can stops reading) is
decoded up to the damage, with a warning line saying where it stops; an
empty one, or one with nothing readable, is refused (exit status 2)."""
from __future__ import annotations

import sys

from .. import args as A
from ..outputs.jsonout import dumps

HELP = "decode a raw serial capture or a python-can log into readable messages"


def add_arguments(p) -> None:
    p.add_argument("file", type=A.input_file, help="capture file")
    p.add_argument("--format", choices=("auto", "serial", "can"), default="auto",
                   help="auto (default): python-can log suffixes are CAN, anything else raw serial")
    p.add_argument("--json", action="store_true", help="one JSON object per message, then the counters")


def run(args) -> int:
    from coiltrack.protocol.capture import decode_file, format_message

    try:
        res = decode_file(args.file, args.format)
    except OSError as exc:
        print(f"coiltrack decode: {args.file}: cannot read it: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except ValueError as exc:           # CaptureFileError: empty, or nothing readable
        print(f"coiltrack decode: {exc}", file=sys.stderr)
        return 2
    if res.damage:
        from ..inputs.infile import warn

        warn("decode", args.file, f"{res.damage}: decoded what is before it")
    for it in res.items:
        if args.json:
            print(dumps({"t": it.t, "src": it.src, "seq": it.seq, "signed": it.signed,
                              "name": it.msg.NAME, "fields": it.msg._asdict()}))
        else:
            print(format_message(it.msg, it.src, it.seq, it.t, it.signed))
    c = res.counters
    if args.json:
        print(dumps({"kind": res.kind, "messages": len(res.items), "counters": c}))
    else:
        bad = {k: v for k, v in c.items() if v and k not in ("frames_ok", "bytes_in", "frames_in", "messages_ok")}
        print(f"-- {len(res.items)} messages ({res.kind}); "
              + (", ".join(f"{k}={v}" for k, v in bad.items()) if bad else "no bad frames"))
    return 0
