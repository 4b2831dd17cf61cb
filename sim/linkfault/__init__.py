"""Link degraders for tests: a loopback UDP proxy for MAVLink and a TCP proxy for the SITL camera
link, each playing a seeded script (drop, delay with jitter, duplicate, reorder, blackout; partial
frames, lost frames, stalls, reconnects) and stopping by itself.  127.0.0.1 only."""

from .script import (
    BOTH,
    DROP_FRAMES,
    PARTIAL_FRAME,
    RECONNECT,
    STALL,
    TO_RUNTIME,
    TO_VEHICLE,
    Impairment,
    LinkScriptError,
    ScriptClock,
    StreamFault,
)
from .tcp import StreamStats, TcpLinkProxy
from .udp import LinkStats, UdpLinkProxy

__all__ = [
    "BOTH", "DROP_FRAMES", "PARTIAL_FRAME", "RECONNECT", "STALL", "TO_RUNTIME", "TO_VEHICLE", "Impairment",
    "LinkScriptError", "LinkStats", "ScriptClock", "StreamFault", "StreamStats", "TcpLinkProxy", "UdpLinkProxy",
]  # fmt: skip
