"""The gateway's own messages to a client whose engine vanished: the room's room_stopped (a
text frame) and the close frame that ends its stream (RFC 6455: server frames are
unmasked, their lengths in the header). Where a stream stands (between two messages, the
room the client is in) is followed by the gateway's pump (native/net/follow.hpp)."""

from __future__ import annotations

import json

from ...game.wire.wsframe import OP_CLOSE, OP_TEXT, frame_header


def text_frame(msg: dict[str, object]) -> bytes:
    """A server's (unmasked) text frame holding ``msg`` as compact JSON, as the engine
    writes it."""
    payload = json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()
    return frame_header(OP_TEXT, len(payload)) + payload


def close_frame(code: int, reason: str) -> bytes:
    """A server's (unmasked) close frame."""
    payload = code.to_bytes(2, "big") + reason.encode()[:123]
    return frame_header(OP_CLOSE, len(payload)) + payload
