"""The replay index's interface (``ReplayIndex``), which its two drivers implement:
``storage.sqlite.SqliteIndex`` (the data directory's ``index.sqlite``) and
``storage.postgres.PostgresIndex`` (one index shared by a cluster's hosts, ``--db``), both
running the SQL of ``storage.sql.SqlIndex``; and what goes with any index: its retention,
the keys private and owned rounds are kept under, and the error of an index that is away.

Retention (``Retention``): an index keeps at most ``max_bytes`` of indexed rounds and none
older than ``max_age_s``; the oldest rounds go first, each one's index row and file together
(the files renamed aside, the rows' deletion committed, the files removed; a crash in
between is resolved at the next start), at most ``PRUNE_BATCH`` rounds a call: the server
prunes after each save and, in the background, until the backlog is gone (an index opened
over a large backlog serves at once). The newest round is never pruned for size, so the
last round played can always be watched. The rounds of one owner (the address whose room
played them, kept only as ``owner_key``, never listed) keep at most ``max_owner_bytes``:
past that, that owner's oldest go, never another's.

A private room's rounds carry ``access`` (``access_key(room, code)``) in their header and
index row: they are listed and served only to a request that names the room's code.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

LOCK_WAIT_S = 60.0  # how long a write keeps retrying a locked index in all
PRUNE_BATCH = 200  # rounds removed by one prune call (one transaction)


class IndexUnavailable(Exception):
    """The replay index's database cannot be reached or used now (a PostgreSQL index
    whose server is down): one line saying so. Rounds are kept as files meanwhile."""


class ReplayIndex(Protocol):
    """What the server, the HTTP surface and ``clothball replays`` use of a replay index.
    Thread-safe: the server calls it from worker threads."""

    dir: Path  # the data directory; the files are under ``replays``
    replays: Path
    read_only: bool  # lists and serves, writes nothing
    retention: Retention | None
    host: str | None  # whose files the rows name (a shared index: an HTTP address)
    index_error: str | None  # why the index cannot be written now (shared: its server)
    rounds: int  # indexed rounds and their bytes, as of the last write or refresh
    bytes: int
    lock_waits: int  # writes that found the index locked and waited

    def save(self, header: dict[str, Any], records: list[tuple[int, bytes]]
             ) -> dict[str, Any]:
        """Write one round's file, then index it. Returns the index row."""

    def index_many(self, rounds: list[tuple[dict[str, Any], str, int]]) -> None:
        """Index rounds (header, file name under ``replays/``, its size) at once."""

    def reconcile(self) -> int:
        """Index the finished files the index lacks; how many."""

    def retry_index(self) -> None:
        """Write the rows kept back while the index was away."""

    def refresh_usage(self) -> None: ...

    def prune(self, retention: Retention, *, now: float | None = None,
              dry_run: bool = False, limit: int | None = PRUNE_BATCH
              ) -> list[dict[str, Any]]: ...

    def prune_all(self, retention: Retention) -> list[dict[str, Any]]: ...

    def prune_owner(self, retention: Retention, owner: str | None
                    ) -> list[dict[str, Any]]: ...

    def list(self, limit: int = 100, offset: int = 0, room_id: str | None = None, *,
             player: str | None = None, code: str | None = None) -> list[dict[str, Any]]:
        """Newest first, as the HTTP API lists (private rounds only with their code)."""

    def count(self, room_id: str | None = None, *, player: str | None = None,
              code: str | None = None) -> int: ...

    def list_all(self, limit: int = 100, room_id: str | None = None,
                 player: str | None = None) -> list[dict[str, Any]]:
        """Private rounds too: the host's own view (``clothball replays list``)."""

    def count_all(self, room_id: str | None = None, player: str | None = None) -> int: ...

    def get(self, rid: str) -> dict[str, Any] | None: ...

    def file_of(self, rid: str) -> Path | None: ...

    def path_of(self, rid: str, code: str | None = None) -> Path | None: ...

    def locate(self, rid: str, code: str | None = None) -> Path | str | None:
        """A path here, a download URL on the host that holds it, or None."""

    def still_there(self) -> bool:
        """The index this one has open is still the data directory's."""

    def lock_is_free(self) -> bool:
        """Whether a write could take the index's lock now."""

    def close(self) -> None: ...


@dataclass(frozen=True)
class Retention:
    """How much the store keeps: indexed rounds' bytes in all, and their age (by end)."""

    max_bytes: int = 2 << 30
    max_age_s: float = 30 * 86400.0
    max_owner_bytes: int | None = None  # one owner's rounds (None: only max_bytes)

    @classmethod
    def from_limits(cls, limits: Any) -> Retention:
        """From ``server.limits.Limits``' ``replays_max_mib``, ``replays_max_days`` and
        ``replays_address_share``."""
        total = int(limits.replays_max_mib * 2**20)
        return cls(total, limits.replays_max_days * 86400.0,
                   int(total * limits.replays_address_share))

    def describe(self) -> str:
        return f"at most {self.max_bytes / 2**20:g} MiB, {self.max_age_s / 86400:g} days"


def owner_key(address: str) -> str:
    """What a round's owner (the address that created its room) is kept as: a hash, so the
    index holds no address; it is never listed."""
    return hashlib.sha256(f"clothball-owner:{address}".encode()).hexdigest()[:32]


def access_key(room_id: str, code: str) -> str:
    """What a private room's rounds are locked with: a hash of its id and join code (the
    code itself is never stored)."""
    return hashlib.sha256(f"clothball-replay:{room_id}:{code}".encode()).hexdigest()


def player_names(players: Any) -> set[str]:
    """The names a round is found by (``?player=``): each seat's, and everyone who held a
    seat during the round (``held_by``: a player who took it mid-round, or left it)."""
    names: set[str] = set()
    for p in players if isinstance(players, list) else ():
        if not isinstance(p, dict):
            continue
        held = p.get("held_by")
        for who in [p, *(held if isinstance(held, list) else ())]:
            if isinstance(who, dict) and isinstance(who.get("name"), str):
                names.add(who["name"])
    return names

