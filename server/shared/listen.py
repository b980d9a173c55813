"""What a host's listening sockets are sized for: a burst of connections at once (issue 43:
2 048 websocket upgrades) must each be answered, never cut.

``ACCEPT_BACKLOG`` is the accept queue asked of every listening socket of a host: the
public port (a process alone, or each gateway's ``SO_REUSEPORT`` socket) and the engine's
Unix socket its gateways connect to, one connection per client. The kernel holds it to
``net.core.somaxconn`` (4 096 by default since Linux 5.4; 128 before). A TCP connection
past a full queue is not lost: the kernel drops its handshake's last packet and the client
sends it again (a second later, then 3, 7 ...). A Unix connection past one is refused at
once (``EAGAIN``): a gateway tries again (``server.gateway.relay.connect_engine``).

``raise_open_files`` lifts the soft limit of open files to the hard one: each client of a
host is a socket in a gateway and one in the engine (two in a gateway that relays), past
a soft limit of 1 024 at a few hundred clients."""

from __future__ import annotations

import resource

ACCEPT_BACKLOG = 4096


def raise_open_files() -> int:
    """The soft ``RLIMIT_NOFILE`` up to the hard limit; returns the soft limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    return soft
