"""The contract between the gateway and the drive: everything both sides of the bus agree on.

Both :mod:`gateway` and :mod:`plant` import this package; it imports neither (nor anything
else of ours). One home per concept:

=====================  ================================================================
module                 what
=====================  ================================================================
:mod:`dbc.codec`       ``drive.eds`` / ``drive.dbc`` paths, the fast PDO codec, scalings
:mod:`dbc.frame`       a signal's encoding and place in a frame; packing by struct or cantools
:mod:`dbc.busdbc`      the built-in DBCs of the whole bus, for any node (third-party tools)
:mod:`dbc.signals`     the PDO signal groups and which message carries which frame
:mod:`dbc.cia301`      NMT states and commands, COB-ID bases, SYNC counter, EMCY codes
:mod:`dbc.cia402`      power states, statusword decoding, controlword commands
:mod:`dbc.modes`       drive modes, setpoint frames, RPDO apply rule (enums)
:mod:`dbc.timing`      the sampled timing contract of a cycle (period, delay, frame)
:mod:`dbc.motor`       motor parameters of model (1) (what 0x2200 holds)
:mod:`dbc.bus`         opening a python-can bus from options/config, with user errors
=====================  ================================================================

The codec's names are re-exported here (``from dbc import load_codec``).
"""

from dbc.codec import (
    AB_DBC_PATH,
    DBC_PATH,
    EDS_PATH,
    INT_SIGNALS,
    STANDARD_DBC_PATH,
    WRAPPING_SIGNALS,
    MessageCodec,
    PdoCodec,
    SignalSpec,
    load_codec,
    load_database,
    message_codec,
    parse_dbc,
    scaling,
    signal_specs,
)

__all__ = [
    "AB_DBC_PATH",
    "DBC_PATH",
    "EDS_PATH",
    "INT_SIGNALS",
    "STANDARD_DBC_PATH",
    "WRAPPING_SIGNALS",
    "MessageCodec",
    "PdoCodec",
    "SignalSpec",
    "load_codec",
    "load_database",
    "message_codec",
    "parse_dbc",
    "scaling",
    "signal_specs",
]
