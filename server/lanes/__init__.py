"""The engine's side of the data plane (docs/architecture.md). Every seated player's HIPs in
and every CORNER and MESH out are served by a gateway's native pump (``native/net``), from
the frame loops' memory (their block, their mesh board): a gateway process's, or the one
on the engine's own port, in the engine's process.

``local`` (``LocalLink``: the engine's own gateway's link, reading that memory in place),
``control`` (the engine's control socket that passes the memory to its gateway processes,
whose ``EngineLink`` is in ``server.gateway``). What a lane is, and the lane message, are
``server.shared.lanes``.
"""
