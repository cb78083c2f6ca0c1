"""Export the CAN messages as a DBC file (cantools). Messages that fit one
classic frame, and the bus forms of HEARTBEAT, TIME_SYNC, COIL_PULSE_CMD,
COIL_STATUS (protocol v3) and TIME_SYNC_REPLY (v4), are described as that frame; the others as their
single CAN FD frame (on a classic bus: the reassembled payload). All are on the identifier with node bits zero;
load with ``cantools.database.load_file(path, frame_id_mask=0x7C0)``. See
docs/protocol.md."""
from __future__ import annotations

from .. import args as A

HELP = "export the CAN messages as a DBC file"


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", type=A.output_path, help="DBC file to write (default: standard output)")


def run(args) -> int:
    from coiltrack.protocol.dbc import dbc_string

    text = dbc_string()
    if args.output:
        with open(args.output, "w", newline="\n") as fh:
            fh.write(text)
        print(f"DBC written to {args.output}")
    else:
        print(text, end="")
    return 0
