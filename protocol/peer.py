"""Peer admission: a node that speaks another schema is refused."""
from __future__ import annotations

from .errors import SchemaMismatchError
from .schema import (PROTOCOL_VERSION, ROLE_COIL_DRIVER, ROLE_FIRMWARE, ROLE_MONITOR, ROLE_SENSOR,
                     SCHEMA_HASH)

ROLE_NAMES = {ROLE_FIRMWARE: "firmware", ROLE_COIL_DRIVER: "coil driver", ROLE_SENSOR: "sensor",
              ROLE_MONITOR: "monitor"}


def role_name(role: int) -> str:
    return ROLE_NAMES.get(role, f"role {role}")


def check_peer(heartbeat, version: int = PROTOCOL_VERSION, schema_hash: int = SCHEMA_HASH):
    """Admit a peer from its HEARTBEAT, or raise :class:`SchemaMismatchError`.

    The heartbeat carries the sender's protocol version and the 32-bit hash
    of its schema table (``protocol.schema.schema_hash``). Both must equal
    ours: a peer built from another table would misread or mis-CRC frames
    (the per-message CRC extra catches most of it frame by frame; this
    catches it once, with a message a person can act on). Returns the
    heartbeat when the peer is admitted.
    """
    if getattr(heartbeat, "NAME", None) != "HEARTBEAT":
        raise TypeError(f"check_peer needs a HEARTBEAT message, got {type(heartbeat).__name__}")
    who = f"node {heartbeat.node} ({role_name(heartbeat.role)})"
    problems = []
    if heartbeat.proto_version != version:
        problems.append(f"protocol version {heartbeat.proto_version}, this node speaks {version}")
    if heartbeat.schema_hash != schema_hash:
        problems.append(f"schema hash {heartbeat.schema_hash:#010x}, this node's is {schema_hash:#010x}")
    if problems:
        raise SchemaMismatchError(
            f"{who} refused: it reports " + " and ".join(problems)
            + "; both ends must be built from the same protocol/schema.py "
              "(compare `coiltrack schema --markdown` on each side)")
    return heartbeat
