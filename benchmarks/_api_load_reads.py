"""api_load's read load: REST clients in a process of their own, each on one keep-alive connection."""

from __future__ import annotations

import asyncio
import gc
import random
import resource
import time
from array import array
from collections import Counter

# Route families of the read mix and their share of requests.
FAMILIES = ("list", "robot_info", "skill_info", "component_info")
INFO_FAMILIES = FAMILIES[1:]


def pick_path(rnd: random.Random, fleet: dict, list_share: float) -> tuple[int, str]:
    """Pick one read of the mix: its route family and its path."""
    if rnd.random() < list_share:
        return 0, "/api/robot"
    family = rnd.randrange(1, 4)
    base = f"/api/robot/{rnd.choice(fleet['robots'])}"
    if family == 1:
        return 1, f"{base}/info"
    base += f"/skill/{rnd.choice(fleet['skills'])}"
    if family == 2:
        return 2, f"{base}/info"
    return 3, f"{base}/component/{rnd.choice(fleet['components'])}/info"


class KeepAliveConnection:
    """One keep-alive HTTP/1.1 connection that sends GETs and reads whole answers, and nothing more.

    The load client must cost far less than the server it measures: httpx spent ~5 ms of CPU
    per request here (its pool scans every connection per request, and httpcore retries a
    failed `import sniffio` each time), more than daphne itself, so a starved client's own
    lag was counted as server latency.
    """

    def __init__(self, host: str, port: int, headers: dict[str, str]) -> None:
        self.host, self.port = host, port
        self.head = "".join(f"{key}: {value}\r\n" for key, value in {"Host": f"{host}:{port}", **headers}.items())
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self, path: str) -> tuple[int, bytes, bool]:
        """Send a GET and return its status, body (as sent, maybe gzipped) and whether it was gzipped."""
        if self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        assert self.reader is not None
        try:
            self.writer.write(f"GET {path} HTTP/1.1\r\n{self.head}\r\n".encode())
            head = await self.reader.readuntil(b"\r\n\r\n")
            lines = head.decode("latin-1").split("\r\n")
            status = int(lines[0].split(" ", 2)[1])
            fields = {}
            for line in lines[1:]:
                key, _, value = line.partition(":")
                fields[key.strip().lower()] = value.strip()
            if "content-length" in fields:
                body = await self.reader.readexactly(int(fields["content-length"]))
            elif fields.get("transfer-encoding", "").lower() == "chunked":
                body = await self._chunked()
            else:
                body = await self.reader.read()
                fields["connection"] = "close"
        except (OSError, asyncio.IncompleteReadError, ValueError, IndexError):
            await self.close()
            raise
        if fields.get("connection", "").lower() == "close":
            await self.close()
        return status, body, fields.get("content-encoding") == "gzip"

    async def _chunked(self) -> bytes:
        assert self.reader is not None
        parts = []
        while True:
            size = int((await self.reader.readuntil(b"\r\n")).split(b";")[0], 16)
            parts.append(await self.reader.readexactly(size + 2))
            if size == 0:
                return b"".join(part[:-2] for part in parts)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.reader = self.writer = None


async def read_load(urls: list[str], token: str, fleet: dict, args: dict) -> dict:
    """Each client reads at `client_rate` per second (open loop), or back to back when it is 0.

    Clients are spread over the daphne processes in `urls` in turn (no stickiness).

    Open-loop latency is measured from when a request was due, so a server that falls
    behind is charged for the wait too (no coordinated omission).
    """
    import gzip
    from urllib.parse import urlsplit

    t0 = time.time() + args["warmup"]
    t1 = t0 + args["duration"]
    samples = [array("d") for _ in FAMILIES]  # latency in seconds, requests started in [t0, t1]
    errors: Counter[str] = Counter()
    bodies: dict[int, tuple[bytes, bool]] = {}
    wheres = [urlsplit(url) for url in urls]
    # Like a browser or httpx: accept gzip, so the server compresses the fleet as for real clients.
    headers = {"Authorization": f"Token {token}", "Accept-Encoding": "gzip"}

    rate = args["client_rate"]

    async def client(index: int) -> None:
        rnd = random.Random(index)
        where = wheres[index % len(wheres)]
        http = KeepAliveConnection(where.hostname or "127.0.0.1", where.port or 80, headers)
        due = time.time() + (rnd.random() / rate if rate else 0.0)
        try:
            while True:
                if rate:
                    wait = due - time.time()
                    if wait > 0:
                        await asyncio.sleep(wait)
                    start, due = due, due + 1.0 / rate
                else:
                    start = time.time()
                if start >= t1:
                    return
                family, path = pick_path(rnd, fleet, args["list_share"])
                try:
                    status, body, gzipped = await asyncio.wait_for(http.get(path), 60)
                except (OSError, asyncio.IncompleteReadError, ValueError, IndexError, TimeoutError) as exc:
                    errors[type(exc).__name__] += 1
                    continue
                elapsed = time.time() - start
                if status != 200:
                    errors[f"HTTP {status}"] += 1
                    continue
                bodies[family] = (body, gzipped)
                if start >= t0:
                    samples[family].append(elapsed)
        finally:
            await http.close()

    cpu0 = sum(resource.getrusage(resource.RUSAGE_SELF)[:2])
    await asyncio.gather(*(client(i) for i in range(args["clients"])))
    cpu = sum(resource.getrusage(resource.RUSAGE_SELF)[:2]) - cpu0
    # Sizes as the application sees them: decompressed, once per route family, after the clock stopped.
    sizes = {family: len(gzip.decompress(body) if gzipped else body) for family, (body, gzipped) in bodies.items()}
    return {
        "t0": t0,
        "t1": t1,
        "samples": [s.tobytes() for s in samples],
        "errors": dict(errors),
        "sizes": sizes,
        "cpu_percent": 100 * cpu / (args["warmup"] + args["duration"]),
    }


def load_main(index, urls, start_event, stop_event, results, token, fleet, args) -> None:
    """Entry point of the load process: read when told to start, then report."""
    # The fork inherits the parent's Django and fleet objects: without this, a full collection
    # in the load client pauses every request in flight and is counted as server latency.
    gc.freeze()
    start_event.wait()
    try:
        results.put(asyncio.run(read_load(urls, token, fleet, args)))
    except BaseException as exc:
        results.put({"crash": repr(exc)})
