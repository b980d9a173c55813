"""``clothball bench --upgrades K``: K websocket upgrades at once to a ``clothball host``,
and what each got back (issue 43: a burst of connections gets answers).

A ``clothball host --workers N`` of its own (``--upgrades-workers``, default 4; its per-address and
total client limits raised so that every upgrade may be served, ``--upgrades-limit``), then
K connections from 127.0.0.1 opened at once by a client process of their own (so that its
CPU is not the host's), each sending one websocket upgrade request and reading until the
answer's head is complete, the connection ends or ``--upgrades-timeout`` seconds pass. Each
is counted by what it got: ``101`` (upgraded), ``503`` (the documented refusal), another
status, ``closed`` (the connection ended with no HTTP answer: the failure this bench is
for), ``timeout`` (nothing by the deadline) or ``connect_failed``. The upgraded ones are then
closed (a close frame, then the socket); the host is stopped.

``burst(host, port, k, timeout)`` is the client side alone, for the tests."""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from ...game.wire.wsframe import OP_CLOSE, ZERO_KEY, masked_frame
from ..shared.listen import raise_open_files

HEAD_MAX = 8192  # an answer's head longer than this is "other"


def configure_upgrade_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("upgrade burst (--upgrades)")
    g.add_argument("--upgrades", type=int, default=0, metavar="K",
                   help="K websocket upgrades at once to a `clothball host --workers N` of its "
                        "own; printed: how many got 101, 503, another answer, none (closed or "
                        "timed out); exit status 1 when any got none")
    g.add_argument("--upgrades-workers", type=int, default=4, metavar="N",
                   help="--upgrades: the host's --workers (default %(default)s)")
    g.add_argument("--upgrades-timeout", type=float, default=30.0, metavar="S",
                   help="--upgrades: seconds each connection waits for its answer (default "
                        "%(default)s)")
    g.add_argument("--upgrades-limit", type=int, default=None, metavar="C",
                   help="--upgrades: the host's max_clients and conns_per_address (default: "
                        "K + 64, so that every upgrade may be served; lower to see 503s)")


def _request(host: str, port: int) -> bytes:
    key = base64.b64encode(os.urandom(16)).decode()
    return (f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n").encode()


async def _one(host: str, port: int, deadline: float, gate: asyncio.Event,
               held: list[socket.socket]) -> str:
    """One connection: its upgrade and what came back."""
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setblocking(False)
    await gate.wait()  # every connection starts together
    try:
        async with asyncio.timeout_at(deadline):
            try:
                await loop.sock_connect(sock, (host, port))
            except OSError:
                sock.close()
                return "connect_failed"
            try:
                await loop.sock_sendall(sock, _request(host, port))
                got = b""
                while b"\r\n\r\n" not in got and len(got) < HEAD_MAX:
                    chunk = await loop.sock_recv(sock, 4096)
                    if not chunk:
                        break
                    got += chunk
            except OSError:  # reset
                got = b""
    except TimeoutError:
        sock.close()
        return "timeout"
    if not got:
        sock.close()
        return "closed"
    line = got.split(b"\r\n", 1)[0].split()
    status = line[1].decode(errors="replace") if len(line) >= 2 else "junk"
    if status == "101":
        held.append(sock)  # closed after the burst, not while others still wait
    else:
        sock.close()
    return status if status in ("101", "503") else f"other {status}"


async def _burst(host: str, port: int, k: int, timeout: float) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    gate = asyncio.Event()
    held: list[socket.socket] = []
    deadline = loop.time() + timeout
    tasks = [asyncio.ensure_future(_one(host, port, deadline, gate, held)) for _ in range(k)]
    await asyncio.sleep(0)  # every task waits at the gate
    t0 = time.perf_counter()
    gate.set()
    outcomes = await asyncio.gather(*tasks)
    wall = time.perf_counter() - t0
    close = masked_frame(OP_CLOSE, (1000).to_bytes(2, "big"), ZERO_KEY)
    for s in held:
        try:
            s.send(close)
        except OSError:
            pass
        s.close()
    counts = Counter(outcomes)
    return {"asked": k, "counts": dict(sorted(counts.items())),
            "answered": sum(v for o, v in counts.items() if o not in ("closed", "timeout",
                                                                        "connect_failed")),
            "unanswered": counts["closed"] + counts["timeout"] + counts["connect_failed"],
            "seconds": wall}


def burst(host: str, port: int, k: int, timeout: float = 30.0) -> dict[str, Any]:
    """``k`` websocket upgrades at once to ``host:port`` from this process (its own event
    loop); what each got, counted (``counts``), the ``answered`` (an HTTP status line came)
    and ``unanswered`` (closed with none, timed out, not connected)."""
    raise_open_files()
    return asyncio.run(_burst(host, port, k, timeout))


def burst_in_process(host: str, port: int, k: int, timeout: float = 30.0) -> dict[str, Any]:
    """``burst`` in a Python process of its own (the burst's CPU not the caller's)."""
    out = subprocess.run(
        [sys.executable, "-m", "clothball.server.bench.upgradebench", "--client", host,
         str(port), str(k), repr(timeout)],
        capture_output=True, text=True, timeout=timeout + 60, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"the burst's client failed: {out.stderr.strip()[-400:]}")
    return dict(json.loads(out.stdout))


def run_upgrades(args: argparse.Namespace) -> int:
    from ..hostproc import bench_host

    k = args.upgrades
    if k < 1:
        print(f"clothball bench: --upgrades must be at least 1, got {k}", file=sys.stderr)
        return 2
    workers = args.upgrades_workers
    if workers < 1:
        print(f"clothball bench: --upgrades-workers must be at least 1, got {workers}",
              file=sys.stderr)
        return 2
    limit = args.upgrades_limit if args.upgrades_limit is not None else k + 64
    raise_open_files()
    with bench_host("--limit", f"max_clients={limit}", "--limit", f"conns_per_address={limit}",
                    "--limit", "hello_timeout=60", workers=workers) as url:
        if url is None:
            return 1
        time.sleep(1.0)  # its gateways listen too
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        result = burst_in_process("127.0.0.1", port, k, args.upgrades_timeout)
    result.update(workers=workers, limit=limit, cpus=os.cpu_count())
    c = result["counts"]
    print(f"{k} upgrades at once to clothball host --workers {workers} (max_clients "
          f"{limit}): {c.get('101', 0)} upgraded, {c.get('503', 0)} refused 503, "
          f"{result['answered'] - c.get('101', 0) - c.get('503', 0)} other answers, "
          f"{result['unanswered']} unanswered ({', '.join(f'{o} {n}' for o, n in c.items())}) "
          f"in {result['seconds']:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0 if result["unanswered"] == 0 else 1


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--client":  # burst_in_process's child
        host, port, k, timeout = argv[1], int(argv[2]), int(argv[3]), float(argv[4])
        print(json.dumps(burst(host, port, k, timeout)))
        return 0
    print("run through `clothball bench --upgrades K`", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
