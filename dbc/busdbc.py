"""The DBC of a run's whole bus, for third-party tools, for any node.

The built-in DBCs describe every frame of a run against the emulated drive, drive node 1
and gateway node 127: its PDOs, NMT, SYNC, EMCY, both heartbeats (the boot-up is the
heartbeat with state 0) and SDO, with value tables for the controlword, the statusword, the
NMT and EMCY codes and the modes of operation. No two messages share an id, so every DBC
tool decodes them: ``drive.dbc`` has the (d, q) setpoints (RPDO2), ``drive_ab.dbc`` the same
bus with the (a, b) setpoints (RPDO2_AB, the alternative mapping on RPDO2's COB-ID), and
``standard.dbc`` the drive in CiA 402's standard cyclic modes (CST, CSV).

:func:`bus_dbc` gives that text for another node: every id of the drive's node-relative
COB-IDs (EMCY, PDOs, SDO, heartbeat) moved to ``node``, the gateway's heartbeat to
``gateway_node``; NMT and SYNC stay. Text in, text out: nothing else of the file changes.
"""

from __future__ import annotations

import re
from pathlib import Path

from dbc.cia301 import HEARTBEAT_BASE
from dbc.codec import AB_DBC_PATH, DBC_NODE_ID, DBC_PATH, STANDARD_DBC_PATH
from dbc.modes import SetpointFrame

__all__ = ["DEFAULT_GATEWAY_NODE", "builtin_dbc", "bus_dbc"]

#: The gateway's own node id in the built-in DBCs (its heartbeat).
DEFAULT_GATEWAY_NODE = 0x7F
#: How the built-in DBCs' database comment names their nodes.
_NODES = f"drive node {DBC_NODE_ID}, gateway node {DEFAULT_GATEWAY_NODE}"
#: A message id where a DBC line names one (messages, comments, value tables, attributes).
_ID = re.compile(r'^((?:CM_ |BA_ "[^"]*" )?(?:BO_|SG_)|VAL_|SIG_VALTYPE_|BO_TX_BU_|SG_MUL_VAL_'
                 r"|SIG_GROUP_) (\d+)\b", re.MULTILINE)


def builtin_dbc(frame: SetpointFrame = SetpointFrame.DQ, standard: bool = False) -> Path:
    """The built-in DBC of a run: the standard modes' (``standard``; they have no setpoint
    frame), else the vector modes' with the setpoints in ``frame``."""
    if standard:
        return STANDARD_DBC_PATH
    return AB_DBC_PATH if frame is SetpointFrame.AB else DBC_PATH


def bus_dbc(node: int = DBC_NODE_ID, frame: SetpointFrame = SetpointFrame.DQ,
            standard: bool = False, gateway_node: int = DEFAULT_GATEWAY_NODE) -> str:
    """The text of :func:`builtin_dbc` with the COB-IDs of drive ``node`` and gateway
    ``gateway_node`` (see the module docstring); ValueError for a node id outside 1..127 or
    both the same (their heartbeats would share an id)."""
    for what, n in (("node", node), ("gateway node", gateway_node)):
        if not 1 <= n <= 127:
            raise ValueError(f"{what} {n}: a CANopen node id is 1..127")
    if node == gateway_node:
        raise ValueError(f"node {node} is also the gateway's node: their heartbeats would "
                         "share a COB-ID; give the gateway another node id")
    path = builtin_dbc(frame, standard)
    text = path.read_text(encoding="utf-8")
    if _NODES not in text:
        raise ValueError(f"{path.name} does not name its nodes as {_NODES!r}")
    gateway_heartbeat = HEARTBEAT_BASE + DEFAULT_GATEWAY_NODE

    def moved(frame_id: int) -> int:
        if frame_id == gateway_heartbeat:
            return HEARTBEAT_BASE + gateway_node
        if frame_id & 0x7F == DBC_NODE_ID and frame_id <= 0x7FF:
            return frame_id - DBC_NODE_ID + node
        return frame_id

    text = _ID.sub(lambda m: f"{m.group(1)} {moved(int(m.group(2)))}", text)
    return text.replace(_NODES, f"drive node {node}, gateway node {gateway_node}")
