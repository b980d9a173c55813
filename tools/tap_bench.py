"""What a binary message costs a websockets server, read and answered through websockets'
public API against through ``game.net.tap`` (issue 39's measured choice).

A server process answers each 28-byte binary message (a HIP's size) with a 104-byte one (a
CORNER's), as the engine's lanes do; one client process sends ``--messages`` of them over
``--clients`` connections at ``--rate`` each and reads the answers. The server's CPU time a
message (user + system, from its own ``resource`` figures) is printed for each way, the
runs alternated ``--repeats`` times; the median of each and their ratio are what to quote.

    python tools/tap_bench.py [--messages 20000] [--clients 8] [--rate 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import resource
import statistics
import subprocess
import sys
import time

ANSWER = bytes(104)


async def serve_main(way: str) -> None:
    from clothball.game.net.tap import TapConnection
    from websockets.asyncio.server import ServerConnection, serve

    class Tapped(TapConnection, ServerConnection):
        pass

    async def handler(ws: ServerConnection) -> None:
        if way == "tap":
            assert isinstance(ws, Tapped)
            ws.listen(lambda data: ws.send_now(ANSWER) or None)
            async for _ in ws:
                ws.message_read()
        else:
            async for _ in ws:
                await ws.send(ANSWER)

    factory = Tapped if way == "tap" else ServerConnection
    async with serve(handler, "127.0.0.1", 0, compression=None,
                     create_connection=factory) as srv:
        port = next(iter(srv.sockets)).getsockname()[1]
        print(port, flush=True)
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
        while (line := await reader.readline()):
            r = resource.getrusage(resource.RUSAGE_SELF)
            print(json.dumps({"cpu": r.ru_utime + r.ru_stime, "line": line.decode().strip()}),
                  flush=True)


async def client_main(port: int, clients: int, messages: int, rate: float) -> float:
    from websockets.asyncio.client import connect

    per = messages // clients
    got = 0

    async def one(k: int) -> None:
        nonlocal got
        async with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
            async def read() -> None:
                nonlocal got
                for _ in range(per):
                    await ws.recv()
                    got += 1

            reading = asyncio.create_task(read())
            start = time.perf_counter() + k / (clients * rate)
            for i in range(per):
                delay = start + i / rate - time.perf_counter()
                if delay > 0:
                    await asyncio.sleep(delay)
                await ws.send(bytes(28))
            await asyncio.wait_for(reading, 60)

    t0 = time.perf_counter()
    await asyncio.gather(*(one(k) for k in range(clients)))
    return time.perf_counter() - t0


def run(way: str, args: argparse.Namespace) -> float:
    srv = subprocess.Popen([sys.executable, __file__, "--serve", way], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True)
    assert srv.stdin is not None and srv.stdout is not None
    try:
        port = int(srv.stdout.readline())

        def cpu() -> float:
            srv.stdin.write("snap\n")
            srv.stdin.flush()
            return float(json.loads(srv.stdout.readline())["cpu"])

        c0 = cpu()
        asyncio.run(client_main(port, args.clients, args.messages, args.rate))
        return (cpu() - c0) / (args.messages // args.clients * args.clients) * 1e6
    finally:
        srv.stdin.close()
        srv.wait(10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--serve", choices=("tap", "websockets"), help=argparse.SUPPRESS)
    ap.add_argument("--messages", type=int, default=20000)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--rate", type=float, default=1000.0, help="messages a second a client")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if args.serve:
        asyncio.run(serve_main(args.serve))
        return
    res: dict[str, list[float]] = {"websockets": [], "tap": []}
    for _ in range(args.repeats):
        for way in res:
            res[way].append(run(way, args))
            print(f"{way:10s} {res[way][-1]:6.1f} us of server CPU a message", flush=True)
    med = {w: statistics.median(v) for w, v in res.items()}
    print(f"median: websockets {med['websockets']:.1f} us, tap {med['tap']:.1f} us a message "
          f"(answer included); ratio {med['websockets'] / med['tap']:.2f}")


if __name__ == "__main__":
    main()
