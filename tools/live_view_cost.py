"""What the live Foxglove view costs the loop: ``python tools/bench.py loop --live``.

Pairs of real-time runs of the loop benchmark in one invocation (``--live-pairs``, default
1), both recorded: the first without the live server, the second with it and a real client
subscribed to every channel (so the server encodes and sends everything it serves). The
difference and the ratio of their figures (tick CPU time and lateness, p50 and p99) are the
live view's cost on the tick, the median over the pairs; the two runs of a pair share the
machine's load of the moment.

The client is a process of its own, as Foxglove is: a client thread in the control process
would take the interpreter's lock from the loop (for up to the 5 ms switch interval at a time)
and the benchmark would measure itself, not the live view.

``python tools/live_view_cost.py PORT`` is that client: it connects (retrying until the server
is up), subscribes to every channel, counts what arrives, and when its stdin closes prints
the counts as one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import websockets
from websockets.typing import Subprotocol

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
#: The per-tick figures compared between the two runs.
FIGURES = ("tick_cpu_us_p99", "tick_cpu_us_p50", "lateness_p99_us", "lateness_p50_us")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _listen(port: int, stop: threading.Event, counts: Counter[str]) -> None:
    """Connect as Foxglove would, subscribe to every advertised channel, count messages by
    topic."""
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
    topics: dict[int, str] = {}
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
                    subs = []
                    for c in op["channels"]:
                        topics[c["id"]] = c["topic"]
                        subs.append({"id": c["id"], "channelId": c["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif raw[:1] == b"\x01":  # message data: subscription id, log time, payload
                counts[topics.get(int.from_bytes(raw[1:5], "little"), "?")] += 1


def client_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="a Foxglove client that counts messages")
    parser.add_argument("port", type=int)
    args = parser.parse_args(argv)
    stop = threading.Event()
    counts: Counter[str] = Counter()

    def wait_stdin() -> None:
        sys.stdin.read()
        stop.set()

    threading.Thread(target=wait_stdin, daemon=True).start()
    asyncio.run(_listen(args.port, stop, counts))
    stop.wait()
    print(
        json.dumps(
            {
                "messages": sum(counts.values()),
                "by_topic": dict(counts),
                "cpu_s": round(time.process_time(), 3),
            }
        )
    )
    return 0


def start_client(port: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, __file__, str(port)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def stop_client(client: subprocess.Popen[str]) -> dict[str, Any]:
    try:
        out, _ = client.communicate("", timeout=30)
    except subprocess.TimeoutExpired:
        client.kill()
        client.communicate()
        return {"messages": -1, "by_topic": {}, "cpu_s": -1.0}
    try:
        counts: dict[str, Any] = json.loads(out)
    except json.JSONDecodeError:
        return {"messages": -1, "by_topic": {}, "cpu_s": -1.0}
    return counts


def compare(
    run: Callable[[argparse.Namespace], dict[str, Any]], args: argparse.Namespace
) -> dict[str, Any]:
    """``args.live_pairs`` pairs of runs, recorded then live; each figure's difference and
    ratio per pair, and their medians (the load of a shared machine moves between the runs of
    a pair less than between pairs). The two runs' own figures are the last pair's."""
    base = argparse.Namespace(
        **{**vars(args), "live": False, "record": True, "live_port": None, "no_naive": True}
    )
    pairs = max(1, int(getattr(args, "live_pairs", 1)))
    added: dict[str, list[float]] = {key: [] for key in FIGURES}
    ratio: dict[str, list[float]] = {key: [] for key in FIGURES}
    outcomes: list[str] = []
    for i in range(pairs):
        print(f"pair {i + 1}/{pairs}: recorded, no live view:", file=sys.stderr)
        recorded = run(base)
        port = free_port()
        client = start_client(port)
        print(
            f"pair {i + 1}/{pairs}: recorded and live on port {port} with a client:",
            file=sys.stderr,
        )
        try:
            live = run(argparse.Namespace(**{**vars(base), "live_port": port}))
        finally:
            counts = stop_client(client)
        outcomes.append(f"{recorded['outcome']}/{live['outcome']}")
        for key in FIGURES:
            added[key].append(live[key] - recorded[key])
            ratio[key].append(live[key] / recorded[key] if recorded[key] else float("nan"))
    out: dict[str, Any] = {f"recorded_{k}": v for k, v in recorded.items()}
    out.update({f"live_{k}": v for k, v in live.items()})
    out["live_messages_received"] = counts["messages"]
    out["live_messages_by_topic"] = counts["by_topic"]
    out["live_client_cpu_s"] = counts["cpu_s"]
    out["live_pairs"] = pairs
    out["live_pair_outcomes"] = outcomes
    for key in FIGURES:
        out[f"live_added_{key}"] = round(statistics.median(added[key]), 1)
        out[f"live_ratio_{key}"] = round(statistics.median(ratio[key]), 3)
        out[f"live_added_{key}_pairs"] = [round(v, 1) for v in added[key]]
    return out


if __name__ == "__main__":
    raise SystemExit(client_main())
