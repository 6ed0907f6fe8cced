"""What the live Foxglove view costs the loop: ``python tools/bench.py loop --live``.

Two real-time runs of the loop benchmark in one invocation, both recorded: the first without
the live server, the second with it and a real client subscribed to every channel (so the
server encodes and sends everything). The difference of their figures is the live view's
cost on the tick; both runs share the machine's load of the moment.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import sys
import threading
from collections.abc import Callable
from typing import Any

import websockets
from websockets.typing import Subprotocol

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _client(port: int, stop: threading.Event, counts: dict[str, int]) -> None:
    """Connect as Foxglove would, subscribe to every advertised channel, count messages."""
    while not stop.is_set():
        try:
            ws = await websockets.connect(
                f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None
            )
            break
        except OSError:
            await asyncio.sleep(0.1)
    else:
        return
    async with ws:
        while not stop.is_set():
            try:
                raw = await asyncio.wait_for(ws.recv(), 0.5)
            except TimeoutError:
                continue
            except websockets.ConnectionClosed:
                return
            if isinstance(raw, str):
                op = json.loads(raw)
                if op.get("op") == "advertise":
                    await ws.send(
                        json.dumps(
                            {
                                "op": "subscribe",
                                "subscriptions": [
                                    {"id": c["id"], "channelId": c["id"]} for c in op["channels"]
                                ],
                            }
                        )
                    )
            else:
                counts["messages"] += 1


def compare(
    run: Callable[[argparse.Namespace], dict[str, Any]], args: argparse.Namespace
) -> dict[str, Any]:
    base = argparse.Namespace(**{**vars(args), "live": False, "record": True, "live_port": None})
    print("recorded, no live view:", file=sys.stderr)
    recorded = run(base)
    port = free_port()
    counts = {"messages": 0}
    stop = threading.Event()
    client = threading.Thread(target=lambda: asyncio.run(_client(port, stop, counts)), daemon=True)
    client.start()
    print(f"recorded and live on port {port} with a subscribed client:", file=sys.stderr)
    try:
        live = run(argparse.Namespace(**{**vars(base), "live_port": port}))
    finally:
        stop.set()
        client.join(5.0)
    out: dict[str, Any] = {f"recorded_{k}": v for k, v in recorded.items()}
    out.update({f"live_{k}": v for k, v in live.items()})
    out["live_messages_received"] = counts["messages"]
    for key in ("tick_cpu_us_p99", "tick_cpu_us_p50", "lateness_p99_us", "lateness_p50_us"):
        out[f"live_added_{key}"] = round(live[key] - recorded[key], 1)
    return out
