"""The first line of every connection a gateway opens to the engine: the client's own
address, in the PROXY protocol's text form (version 1, as HAProxy, nginx and others
write it), so that the engine applies its per-address limits to the client and not to
the gateway. Only the host's own processes can open the engine's socket (a private
directory), so the line is trusted as given. A gateway that serves seated players' lanes
(``server.shared.lanes``) says so with one more word, ``LANES``, at the line's end."""

from __future__ import annotations

import ipaddress

MAX_LINE = 107  # the protocol's bound on the line, CRLF included


class BadLine(ValueError):
    """A first line that is not a PROXY v1 header."""


def encode(peer: tuple[str, int] | None, local: tuple[str, int] | None, *,
           lanes: bool = False) -> bytes:
    """The line for a client at ``peer`` that connected to ``local`` (either unknown:
    ``PROXY UNKNOWN``); ``lanes``: the gateway serves the client's lane."""
    end = b" LANES\r\n" if lanes else b"\r\n"
    if not peer or not local:
        return b"PROXY UNKNOWN" + end
    try:
        src, dst = ipaddress.ip_address(peer[0]), ipaddress.ip_address(local[0])
    except ValueError:
        return b"PROXY UNKNOWN" + end
    if src.version != dst.version:
        return b"PROXY UNKNOWN" + end
    family = "TCP4" if src.version == 4 else "TCP6"
    return f"PROXY {family} {src} {dst} {peer[1]} {local[1]}".encode("ascii") + end


def lanes(line: bytes) -> bool:
    """Whether the gateway that wrote ``line`` serves lanes."""
    return line.endswith(b" LANES\r\n")


def local_port(line: bytes) -> int | None:
    """The port the client connected to, as ``line`` names it (None: ``UNKNOWN``, or not
    a number)."""
    parts = line.rstrip(b"\r\n").split(b" ")
    if parts and parts[-1] == b"LANES":
        parts.pop()
    if len(parts) != 6:
        return None
    try:
        return int(parts[5])
    except ValueError:
        return None


def decode(line: bytes) -> tuple[str, int] | None:
    """The client's address named by ``line`` (CRLF included); None for ``UNKNOWN``.
    ``BadLine`` when it is not a PROXY v1 line."""
    if len(line) > MAX_LINE or not line.endswith(b"\r\n"):
        raise BadLine("not a PROXY line: too long or not ended by CRLF")
    parts = line[:-2].decode("ascii", "replace").split(" ")
    if parts[-1] == "LANES":
        parts.pop()
    if parts[:2] == ["PROXY", "UNKNOWN"]:
        return None
    if len(parts) != 6 or parts[0] != "PROXY" or parts[1] not in ("TCP4", "TCP6"):
        raise BadLine(f"not a PROXY v1 line: {line[:60]!r}")
    try:
        ip = ipaddress.ip_address(parts[2])
        port = int(parts[4])
    except ValueError as e:
        raise BadLine(f"bad address in the PROXY line: {e}") from None
    return str(ip), port
