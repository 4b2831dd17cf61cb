"""The --autopilot URL: which local address the autopilot's pose link arrives at, loopback unless
allowed otherwise.  No MAVLink here, so that `cmnav sitl` can check the URL before it starts
anything (and import it where pymavlink is absent)."""

from __future__ import annotations

from urllib.parse import urlsplit

LOOPBACK = "127.0.0.1"
URL_SCHEMES = ("udp", "udpin")


class AutopilotUrlError(ValueError):
    """An --autopilot URL this follower cannot or will not use."""


def parse_autopilot_url(url: str, allow_remote: bool = False) -> tuple[str, int]:
    """``udp://HOST:PORT`` (or ``udpin://``): the local address to listen on for the
    autopilot's pose link -> (host, port).  A host other than 127.0.0.1 is refused unless
    ``allow_remote`` (a real bench setup)."""
    parts = urlsplit(url)
    if parts.scheme not in URL_SCHEMES or not parts.hostname or parts.path not in ("", "/"):
        raise AutopilotUrlError(
            f"--autopilot {url!r}: expected udp://HOST:PORT, the address the autopilot's MAVLink stream arrives at "
            f"(PX4 SITL's GCS link: udp://127.0.0.1:14550)"
        )
    try:
        port = parts.port
    except ValueError as err:
        raise AutopilotUrlError(f"--autopilot {url!r}: bad port ({err})") from err
    if port is None or not 0 < port < 65536:
        raise AutopilotUrlError(f"--autopilot {url!r}: needs a port in 1..65535, e.g. udp://127.0.0.1:14550")
    if parts.hostname != LOOPBACK and not allow_remote:
        raise AutopilotUrlError(
            f"--autopilot {url!r}: host {parts.hostname} is not {LOOPBACK}; this SITL setup stays on loopback. "
            f"Use udp://{LOOPBACK}:{port}, or pass --allow-remote for an autopilot on another machine"
        )
    return parts.hostname, port
