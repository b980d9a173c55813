"""``docs/protocol.md``'s tables as data: the conformance suite's list of what to check
(``tests/server/test_conformance.py``), so that the doc is the one source of it.

Every Markdown table of the doc must be named by a ``<!-- table: NAME -->`` line before it
(a table without one is an error: nothing the doc promises escapes the suite). ``rows()``
turns the tables into rows with stable ids, ``TABLE:KEY`` for a table's row (``errors:
bad_json``, ``http:/api/rooms``, ``corner:52``) and ``TABLE:KEY.FIELD`` for each field a
message's ``fields`` cell names (``requests:create_room.first_to``, ``events:score.ball``).

``python3 -m tests.server.protocol_doc`` prints the rows as JSON.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"

_NAME = re.compile(r"<!--\s*table:\s*([a-z_]+)\s*-->")
_TICKED = re.compile(r"`([^`]+)`")

# The tables whose rows are messages with a ``fields`` cell, and the column naming them.
MESSAGE_TABLES = {"requests": "type", "replies": "type", "events": "event"}


class DocError(ValueError):
    """The doc's tables cannot be read as the suite needs them."""


@dataclass(frozen=True)
class Table:
    name: str
    columns: tuple[str, ...]
    rows: tuple[dict[str, str], ...]
    line: int  # of the header row, 1-based


@dataclass(frozen=True)
class Row:
    id: str  # "TABLE:KEY" or "TABLE:KEY.FIELD"
    table: str
    key: str  # the row's first column, as a name (backticks and queries dropped)
    field: str | None  # a field of the message ``key`` (message tables), else None
    cells: dict[str, str]  # the row's cells by column (the message's row for a field)
    text: str  # a field's own text in the fields cell ("first_to (1..99, 5)")


def _cells(line: str) -> list[str]:
    inner = line.strip()
    if not (inner.startswith("|") and inner.endswith("|")):
        raise DocError(f"not a table row: {line!r}")
    return [c.strip() for c in re.split(r"(?<!\\)\|", inner[1:-1])]


def tables(text: str | None = None) -> dict[str, Table]:
    """Every table of the doc, by name."""
    lines = (DOC.read_text(encoding="utf-8") if text is None else text).splitlines()
    out: dict[str, Table] = {}
    name: str | None = None
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        m = _NAME.fullmatch(line)
        if m:
            name = m.group(1)
        elif line.startswith("|"):
            if name is None:
                raise DocError(f"line {i + 1}: a table without a '<!-- table: NAME -->' line")
            if name in out:
                raise DocError(f"line {i + 1}: a second table named {name!r}")
            columns = tuple(_cells(line))
            if i + 1 >= len(lines) or not set(lines[i + 1].strip()) <= set("|-: "):
                raise DocError(f"line {i + 2}: the table {name!r} has no separator row")
            rows = []
            j = i + 2
            while j < len(lines) and lines[j].strip().startswith("|"):
                cells = _cells(lines[j])
                if len(cells) != len(columns):
                    raise DocError(f"line {j + 1}: {len(cells)} cells, the table {name!r} has "
                                   f"{len(columns)} columns")
                rows.append(dict(zip(columns, cells, strict=True)))
                j += 1
            out[name] = Table(name, columns, tuple(rows), i + 1)
            name, i = None, j
            continue
        elif line and name is not None:
            raise DocError(f"line {i + 1}: text between '<!-- table: {name} -->' and its table")
        i += 1
    return out


def top_level(cell: str) -> list[str]:
    """``cell`` split at its commas outside brackets and backticks."""
    parts, depth, ticked, cur = [], 0, False, []
    for ch in cell:
        if ch == "`":
            ticked = not ticked
        elif not ticked and ch in "([{":
            depth += 1
        elif not ticked and ch in ")]}":
            depth -= 1
        if ch == "," and depth == 0 and not ticked:
            parts.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    if "".join(cur).strip():
        parts.append("".join(cur).strip())
    return parts


def fields(cell: str) -> list[tuple[str, str]]:
    """The fields a ``fields`` cell names: each top-level part that starts with a
    backticked name, as (name, the part's text)."""
    out = []
    for part in top_level(cell):
        m = re.match(r"`([a-z_]+)`", part)
        if m:
            out.append((m.group(1), part))
    return out


def key_of(cell: str) -> str:
    """A row's first cell as a name: its first backticked text (a path's query dropped),
    or the cell itself (a number)."""
    m = _TICKED.search(cell)
    return (m.group(1) if m else cell).split("?")[0]


def rows(text: str | None = None) -> list[Row]:
    out: list[Row] = []
    for t in tables(text).values():
        for cells in t.rows:
            key = key_of(cells[t.columns[0]])
            out.append(Row(f"{t.name}:{key}", t.name, key, None, cells, cells[t.columns[0]]))
            if t.name in MESSAGE_TABLES:
                for f, part in fields(cells["fields"]):
                    out.append(Row(f"{t.name}:{key}.{f}", t.name, key, f, cells, part))
    ids = [r.id for r in out]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise DocError(f"rows named twice: {sorted(dup)}")
    return out


if __name__ == "__main__":
    print(json.dumps([asdict(r) for r in rows()], indent=1, ensure_ascii=False))
