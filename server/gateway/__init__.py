"""A gateway process of ``clothball host`` (``docs/architecture.md``): one of several that
accept the host's websocket and HTTP connections on its one public port (SO_REUSEPORT)
and carry each to the host's engine over its Unix socket. It imports nothing of the
engine (``pyproject.toml``'s contracts): it starts in a moment and a restart loses only
its own connections."""
