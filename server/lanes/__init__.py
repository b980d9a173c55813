"""The data plane: every seated player's HIPs in and every CORNER and MESH out, served from
the frame loops' shared memory (their block, their mesh board) by one lane code, whatever
the topology (docs/architecture.md).

``lane`` (``Lane``: one client's HIPs, CORNER timing, MESH), ``links`` (``Links``: where a
process finds the blocks and boards, its watched boards and frame wake-up), ``local``
(``LocalLinks``: the engine's, over its own frame loops), ``control`` (the engine's control
socket that passes its blocks to its gateways, whose ``SocketLinks`` is in
``server.gateway``). What a lane is, and the lane message, are ``server.shared.lanes``.
"""
