"""The cloud's Prometheus metrics: one definition of every family, and the `/metrics` exposition.

Several daphne processes and Celery workers (prefork children included) serve one cloud, so
the counters, gauges and histograms live in prometheus_client's multiprocess mode: every
process writes its values to mmap'd files under PROMETHEUS_MULTIPROC_DIR (set by settings to
`<data dir>/prometheus` unless given), and a scrape of any process's `/metrics` sums them. A
per-process port would need Prometheus to discover every daphne and every prefork child.

State that lives in PostgreSQL (robots connected, cloud copies by state) is read from the
database at scrape time instead of being counted, so it is right whichever process changed it.

Hot-path calls (`frame_received`, `points_received`, `dedup_hit`) touch label children
created once at import: an increment is an mmap write, no dict lookup, no lock of ours.
"""

from __future__ import annotations

import atexit
import os
import time
from collections.abc import Callable
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest, multiprocess

NAMESPACE = "bridgeos"
COMMAND_OUTCOMES = ("accepted", "refused", "offline", "timeout")
RECONCILER_ACTIONS = ("restarted", "crashed", "removed", "relaunched", "masters")
# Seconds; commands wait up to BRIDGEOS_COMMAND_WAIT_S (5 s by default) for the robot.
COMMAND_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
BATCH_BUCKETS = (1, 10, 100, 500, 1000, 2500, 5000, 10000, 25000, 50000)
LAG_BUCKETS = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
TASK_BUCKETS = (0.01, 0.05, 0.1, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)


def multiprocess_dir() -> Path | None:
    """Return the directory the processes share their values in, or None in single-process mode."""
    value = os.environ.get("PROMETHEUS_MULTIPROC_DIR")
    return Path(value) if value else None


# --------------------------------------------------------------------------- robot door and ingest

FRAMES_RECEIVED = Counter("frames_received", "WebSocket frames received from robots.", namespace=NAMESPACE)
POINTS_RECEIVED = Counter("metric_points_received", "Metric points received from robots.", namespace=NAMESPACE)
DEDUP_HITS = Counter("dedup_hits", "Robot frames dropped as duplicates of applied ones.", namespace=NAMESPACE)
INGEST_BATCH_ROWS = Histogram(
    "ingest_batch_rows", "Metric rows written per batch.", namespace=NAMESPACE, buckets=BATCH_BUCKETS
)
INGEST_LAG = Histogram(
    "ingest_lag_seconds",
    "Time from a batch's oldest frame arriving to its rows being committed.",
    namespace=NAMESPACE,
    buckets=LAG_BUCKETS,
)
INGEST_ROWS_WRITTEN = Counter("ingest_rows_written", "Metric rows committed.", namespace=NAMESPACE)
INGEST_COPY_ERRORS = Counter(
    "ingest_copy_errors", "Batches or frames the database refused or failed to write.", namespace=NAMESPACE
)
INGEST_PENDING_ROWS = Gauge(
    "ingest_pending_rows",
    "Metric rows received but not yet committed.",
    namespace=NAMESPACE,
    multiprocess_mode="livesum",
)

# --------------------------------------------------------------------------- commands relayed to robots

COMMANDS = Counter("commands", "Commands relayed to robots, by outcome.", ["outcome"], namespace=NAMESPACE)
COMMAND_SECONDS = Histogram(
    "command_seconds",
    "Time from relaying a command to its outcome.",
    ["outcome"],
    namespace=NAMESPACE,
    buckets=COMMAND_BUCKETS,
)
_commands = {outcome: (COMMANDS.labels(outcome), COMMAND_SECONDS.labels(outcome)) for outcome in COMMAND_OUTCOMES}

# --------------------------------------------------------------------------- live feed to dashboards

LIVE_CLIENTS = Gauge(
    "live_clients", "Dashboards and apps connected to /ws/client/.", namespace=NAMESPACE, multiprocess_mode="livesum"
)
LIVE_MESSAGES = Counter("live_messages", "Coalesced live-feed messages sent to the live group.", namespace=NAMESPACE)
LIVE_DROPS = Counter(
    "live_drops", "Live-feed messages that could not be sent (the values are dropped).", namespace=NAMESPACE
)

# --------------------------------------------------------------------------- rosbridge and Foxglove clients

BRIDGE_DROP_PLACES = ("robot_queue", "cloud_queue", "channel_full", "blob_missing")
BRIDGE_CLIENTS = Gauge(
    "bridge_clients",
    "rosbridge and Foxglove clients connected through the cloud, by protocol.",
    ["kind"],
    namespace=NAMESPACE,
    multiprocess_mode="livesum",
)
BRIDGE_FRAMES = Counter(
    "bridge_frames", "Frames sent to rosbridge and Foxglove clients, by protocol.", ["kind"], namespace=NAMESPACE
)
BRIDGE_BYTES = Counter(
    "bridge_bytes", "Bytes sent to rosbridge and Foxglove clients, by protocol.", ["kind"], namespace=NAMESPACE
)
BRIDGE_BLOB_BYTES = Counter(
    "bridge_blob_bytes",
    "Bytes of frames shared by several clients that robots sent once (blobs).",
    namespace=NAMESPACE,
)
BRIDGE_DROPS = Counter(
    "bridge_drops",
    "Messages dropped for slow rosbridge and Foxglove clients, by protocol and where: the robot's queue "
    "for the client, the cloud's, a full channel, or a shared frame that came too late.",
    ["kind", "where"],
    namespace=NAMESPACE,
)

# --------------------------------------------------------------------------- Celery and orchestration

TASKS = Counter("celery_tasks", "Celery tasks finished, by task and outcome.", ["task", "outcome"], namespace=NAMESPACE)
TASK_SECONDS = Histogram(
    "celery_task_seconds",
    "Celery task run time by task and outcome.",
    ["task", "outcome"],
    namespace=NAMESPACE,
    buckets=TASK_BUCKETS,
)
RECONCILER_ACTIONS_TOTAL = Counter(
    "reconciler_actions", "What the reconciler did to cloud copies, by action.", ["action"], namespace=NAMESPACE
)
_reconciler = {action: RECONCILER_ACTIONS_TOTAL.labels(action) for action in RECONCILER_ACTIONS}

# --------------------------------------------------------------------------- HTTP

HTTP_SECONDS = Histogram(
    "http_request_seconds",
    "HTTP request latency by route pattern, method and status class.",
    ["route", "method", "status"],
    namespace=NAMESPACE,
)


# --------------------------------------------------------------------------- recording (one-line calls)


def frame_received() -> None:
    """Count one frame from a robot."""
    FRAMES_RECEIVED.inc()


def points_received(count: int) -> None:
    """Count the metric points of one frame."""
    POINTS_RECEIVED.inc(count)


def bridge_dropped(kind: str, where: str, count: int = 1) -> None:
    """Count messages dropped for a bridge client: where, of BRIDGE_DROP_PLACES."""
    BRIDGE_DROPS.labels(kind, where).inc(count)


def bridge_sent(kind: str, frames: int, size: int) -> None:
    """Count frames sent to a bridge client, and their bytes."""
    BRIDGE_FRAMES.labels(kind).inc(frames)
    BRIDGE_BYTES.labels(kind).inc(size)


def dedup_hit() -> None:
    """Count a duplicate frame dropped by the dedup window."""
    DEDUP_HITS.inc()


def batch_written(rows: int, oldest_added: float) -> None:
    """Record a committed batch: its size and how long its oldest frame waited (monotonic clock)."""
    INGEST_BATCH_ROWS.observe(rows)
    INGEST_ROWS_WRITTEN.inc(rows)
    INGEST_LAG.observe(time.monotonic() - oldest_added)


def copy_failed(count: int = 1) -> None:
    """Count batches or frames the database did not take."""
    INGEST_COPY_ERRORS.inc(count)


def command_finished(outcome: str, started: float) -> None:
    """Record a relayed command's outcome and latency (started on the monotonic clock)."""
    counter, histogram = _commands[outcome]
    counter.inc()
    histogram.observe(time.monotonic() - started)


def reconciled(done: dict[str, int]) -> None:
    """Count what one reconciler round did."""
    for action, child in _reconciler.items():
        if done.get(action):
            child.inc(done[action])


# --------------------------------------------------------------------------- state read at scrape time


def label(value: str) -> str:
    """Escape a label value for the text format."""
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def family(lines: list[str], name: str, doc: str) -> None:
    """Start a gauge family in the text format."""
    lines.append(f"# HELP {name} {doc}")
    lines.append(f"# TYPE {name} gauge")


# Families read from PostgreSQL at scrape time, each added by the app that owns its rows (in its
# AppConfig.ready), so this floor of the apps never imports the apps above it. They are written
# straight to the text format: with a series or two per robot, prometheus_client's generic
# formatter would spend more than the whole 50 ms scrape budget on 1,000 robots.
_database_families: list[Callable[[list[str]], None]] = []


def add_database_families(write: Callable[[list[str]], None]) -> None:
    """Register a writer of families read from the database at every scrape."""
    if write not in _database_families:
        _database_families.append(write)


def database_state() -> bytes:
    """Report the state PostgreSQL holds (robots connected and last seen, cloud copies by state)."""
    lines: list[str] = []
    for write in _database_families:
        write(lines)
    return ("\n".join(lines) + "\n").encode() if lines else b""


def forget_dead_processes(directory: Path) -> None:
    """Drop the live gauges of processes that died without saying so (kill -9 runs no atexit)."""
    for path in directory.glob("gauge_live*_*.db"):
        pid = int(path.stem.rpartition("_")[2])
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            multiprocess.mark_process_dead(pid, str(directory))
        except PermissionError:
            pass  # alive, another user's


def exposition() -> bytes:
    """Return every process's metrics and the database's state in the Prometheus text format."""
    directory = multiprocess_dir()
    if directory is not None:
        forget_dead_processes(directory)
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
    else:
        from prometheus_client import REGISTRY as registry
    return generate_latest(registry) + database_state()


def _forget_this_process() -> None:
    """Drop this process's live gauges (connected clients, pending rows) when it exits."""
    if multiprocess_dir() is not None:
        multiprocess.mark_process_dead(os.getpid())


atexit.register(_forget_this_process)


# --------------------------------------------------------------------------- Celery


def watch_celery_tasks() -> None:
    """Count and time every Celery task by name and outcome (connected once, in the Celery app)."""
    from celery import signals

    started: dict[str, float] = {}

    @signals.task_prerun.connect(weak=False)
    def _started(task_id: str | None = None, **_: object) -> None:
        if task_id:
            started[task_id] = time.perf_counter()

    @signals.task_postrun.connect(weak=False)
    def _finished(task_id: str | None = None, task: object = None, state: str | None = None, **_: object) -> None:
        began = started.pop(task_id or "", None)
        name = getattr(task, "name", None) or "unknown"
        outcome = (state or "unknown").lower()
        TASKS.labels(name, outcome).inc()
        if began is not None:
            TASK_SECONDS.labels(name, outcome).observe(time.perf_counter() - began)

    @signals.worker_process_shutdown.connect(weak=False)
    def _child_exits(**_: object) -> None:
        # Prefork children leave with os._exit, past atexit.
        _forget_this_process()
