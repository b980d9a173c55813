"""Every limit the server puts on what a client may do, in one place.

``docs/security.md`` documents each one (what it bounds, its default, how a client is
told). A host changes them with ``clothball host --limit NAME=VALUE`` (repeatable) and
restricts browser origins with ``--origin URL``; in Python, ``ServerConfig(limits=...)``.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class Limits:
    # --- message size (a larger websocket message closes the connection, 1009) ---------------
    max_message_bytes: int = 65536
    max_control_bytes: int = 4096  # a larger JSON control message is refused (too_big)
    # --- rates, per connection (token buckets: rate per second, burst) -----------------------
    control_rate: float = 20.0
    control_burst: float = 40.0
    binary_rate: float = 1200.0  # HIP messages
    binary_burst: float = 400.0
    error_rate: float = 5.0  # error replies sent; the rest are counted in 'suppressed'
    error_burst: float = 20.0
    abuse_drops: int = 5000  # messages dropped for rate within abuse_window s: closed 1008
    abuse_window: float = 2.0
    # --- connections and rooms ---------------------------------------------------------------
    max_clients: int = 512  # websocket connections in all (more: HTTP 503)
    # The last slots of max_clients (at most an eighth of them) are kept for addresses that
    # hold no connection: a newcomer gets in while others' many connections fill the rest.
    reserved_slots: int = 16
    conns_per_address: int = 32  # from one IP address (more: closed 1008)
    max_rooms: int = 32  # rooms in all (more: server_busy)
    rooms_per_address: int = 4  # rooms created from one IP address and still open
    spectators_per_room: int = 64  # (more: room_full)
    # A room nobody is in (no human player, no spectator) sleeps at once and closes after
    # this long (its creator's seat and a reconnect have this long to come back).
    room_idle_close_s: float = 15.0
    # Admission (server.headroom): a new room is refused (server_busy) when the open rooms'
    # measured cost and its own would pass admit_load of admit_cores (0: the cores this
    # process may use), or of one core for the rooms of one scene; 0: no cost model.
    admit_load: float = 0.75
    admit_cores: float = 0.0
    # And while the frame lateness p99 passes this (or frames are skipped) three seconds
    # running with the server itself using half a core or more, new rooms and wake-ups of
    # sleeping rooms are refused (server_busy); 0: off.
    admit_lateness_ms: float = 5.0
    # --- the replay index over HTTP (/api/replays...), per IP address -----------------------
    index_rate: float = 50.0  # queries a second (token bucket; more: HTTP 429)
    index_burst: float = 100.0
    index_queue: int = 64  # queries waiting for the index's threads in all (more: HTTP 503)
    # --- replay downloads (/api/replays/ID), streamed in 64 KiB chunks ------------------------
    max_downloads: int = 64  # under way at once, in all (more: HTTP 503)
    download_stall_s: float = 30.0  # s a download may wait for its client to read (else cut)
    # --- the replay store's retention (oldest rounds pruned first, file and index row) -------
    replays_max_mib: float = 2048.0  # MiB of recorded rounds kept in all
    # The share of replays_max_mib the rounds of the rooms one address created may keep
    # (past it, that address's oldest go, never anyone else's).
    replays_address_share: float = 0.25
    record_cap_max_s: float = 600.0  # the longest record_cap_s a create_room may ask for
    replays_max_days: float = 30.0  # days a recorded round is kept
    # --- the data directory --------------------------------------------------------------------
    storage_min_free_mib: float = 64.0  # free MiB below which recording pauses ("full")
    storage_check_s: float = 5.0  # s between looks at the data directory (problems, recovery)
    # --- time and slow clients -----------------------------------------------------------------
    hello_timeout: float = 10.0  # s to send the hello (else closed 1008)
    slow_drop_s: float = 5.0  # s a client may leave its socket backed up (else closed 1008)
    max_control_queue: int = 512  # unsent control messages (more: closed 1008)
    max_write_buffer: int = 256 * 1024  # bytes waiting in the socket that count as backed up
    # The kernel's send buffer per connection (SO_SNDBUF; Linux doubles it). Fixed, so a
    # client that stops reading is noticed within seconds and holds at most this much
    # kernel memory, instead of the megabytes TCP autotuning would give it.
    socket_send_buffer: int = 128 * 1024
    lobby_idle_s: float = 60.0  # s a lobby connection may send nothing (else closed 1008)
    ping_interval: float = 20.0  # s between keep-alive pings
    ping_timeout: float = 20.0  # s without a pong: the client is gone (closed 1011)

    def full_for(self, clients: int, held: int) -> str | None:
        """Why a new connection is refused (HTTP 503) with ``clients`` connected and
        ``held`` of them from its address; None: it may connect."""
        if clients >= self.max_clients:
            return f"server full ({self.max_clients} connections)"
        reserved = min(self.reserved_slots, self.max_clients // 8)
        if held and clients >= self.max_clients - reserved:
            return (f"server full for addresses that already hold a connection (the last "
                    f"{reserved} of {self.max_clients} are kept for new addresses)")
        return None

    def replace(self, **changes: float | int) -> Limits:
        return dataclasses.replace(self, **changes)

    def with_setting(self, text: str) -> Limits:
        """``NAME=VALUE`` (as on the command line) applied; ``ValueError`` naming what is
        wrong otherwise. Every limit is a finite positive number (those in ``MAY_BE_OFF``
        may also be 0: off)."""
        name, sep, value = text.partition("=")
        name = name.strip().replace("-", "_")
        known = {f.name: f for f in fields(self)}
        if not sep or name not in known:
            raise ValueError(f"--limit {text!r}: expected NAME=VALUE with NAME one of "
                             f"{', '.join(known)}")
        kind = known[name].type
        try:
            v: float | int = int(value) if kind in (int, "int") else float(value)
        except ValueError:
            raise ValueError(f"--limit {name}: {value!r} is not a number") from None
        if name in MAY_BE_OFF and v == 0:
            return self.replace(**{name: v})
        if not (math.isfinite(v) and v > 0):
            off = " (or 0: off)" if name in MAY_BE_OFF else ""
            raise ValueError(f"--limit {name}: must be a finite number > 0{off}, got {value!r}")
        return self.replace(**{name: v})


# Limits that 0 turns off (admit_cores 0: the cores this process may use).
MAY_BE_OFF = frozenset({"admit_lateness_ms", "admit_load", "admit_cores"})


def parse_origins(origins: list[str] | None) -> tuple[str, ...] | None:
    """The websocket origins allowed besides the server's own, from ``--origin`` values
    (None: only its own; ``*``: any)."""
    if not origins:
        return None
    out = []
    for o in origins:
        o = o.strip().rstrip("/")
        if o == "*":
            out.append(o)
            continue
        if not o.startswith(("http://", "https://")) or any(c in o for c in " \t\r\n"):
            raise ValueError(f"--origin {o!r}: expected an origin such as https://example.org "
                             "(or * for any)")
        out.append(o)
    return tuple(out)


def parse_trusted_proxies(values: list[str] | None
                          ) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
    """The ``--trusted-proxy`` values (an address or a network such as 10.0.0.0/8): the
    peers whose ``X-Forwarded-For`` names the client."""
    out = []
    for v in values or ():
        try:
            out.append(ipaddress.ip_network(v.strip(), strict=False))
        except ValueError:
            raise ValueError(f"--trusted-proxy {v!r}: expected an IP address or network, "
                             "e.g. 127.0.0.1 or 10.0.0.0/8") from None
    return tuple(out)


DEFAULT = Limits()

__all__ = ["DEFAULT", "Limits", "parse_origins", "parse_trusted_proxies"]
