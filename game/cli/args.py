"""Argument types shared by the commands: a bad value is refused by argparse with the
allowed range named (``clothball host: error: argument --port: ...``), never a traceback
later on."""

from __future__ import annotations

import argparse
import urllib.parse
from collections.abc import Callable


def int_in(lo: int, hi: int, what: str = "a whole number") -> Callable[[str], int]:
    """An argparse type: an integer in lo..hi."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what} in {lo}..{hi}, got {text!r}"
                                             ) from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be {what} in {lo}..{hi}, got {value}")
        return value

    return parse


PORT = int_in(0, 65535, "a port number (0: any free port)")
FIRST_TO = int_in(1, 99, "the points that win a match")
WORKERS = int_in(1, 64, "a number of server processes")


def redis_url(text: str) -> str:
    """An argparse type: a Redis URL (redis://HOST:PORT/DB, rediss:// or unix://)."""
    parts = urllib.parse.urlsplit(text)
    if parts.scheme not in ("redis", "rediss", "unix") or not (parts.netloc or parts.path):
        raise argparse.ArgumentTypeError(
            f"must be a Redis URL such as redis://127.0.0.1:6379/0, got {text!r}")
    return text


def postgres_url(text: str) -> str:
    """An argparse type: a PostgreSQL URL (postgresql://USER@HOST:PORT/DB)."""
    parts = urllib.parse.urlsplit(text)
    if parts.scheme not in ("postgresql", "postgres") or not (parts.netloc or parts.query):
        raise argparse.ArgumentTypeError(
            f"must be a PostgreSQL URL such as postgresql://clothball@127.0.0.1:5432/clothball,"
            f" got {text!r}")
    return text


def ws_url(text: str) -> str:
    """An argparse type: a game server's websocket address, ws://HOST:PORT/ws."""
    parts = urllib.parse.urlsplit(text)
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        hint = ""
        if parts.scheme in ("http", "https") and parts.netloc:
            hint = f"; the game server's websocket is ws{parts.scheme[4:]}://{parts.netloc}/ws"
        raise argparse.ArgumentTypeError(
            f"must be a websocket address like ws://HOST:PORT/ws, got {text!r}{hint}")
    return text
