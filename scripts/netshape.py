#!/usr/bin/env python3
"""Shape the robot-cloud network: a "cloud" namespace behind a link with Wi-Fi/4G/3G conditions.

    scripts/netshape.py presets                        # the presets and what they mean
    scripts/netshape.py up --preset 4g                 # hold a link until Ctrl-C, printing its addresses
    scripts/netshape.py run --preset 3g -- CMD ARGS    # run CMD in the cloud namespace, then remove the link
    scripts/netshape.py list                           # the bosuc- namespaces and their owners
    scripts/netshape.py clean [--all]                  # remove links whose owner is gone (or all)

Bandwidth is shaped with tc (token buckets), delay, jitter and loss by a user-space relay
(benchmarks/_netshape.py, which benchmarks import). Needs root.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import _netshape as netshape  # the library lives beside the benchmarks that use it


def conditions(args: argparse.Namespace) -> netshape.Conditions:
    """Build the link's conditions from a preset and the options overriding it."""
    try:
        return netshape.conditions_for(
            args.preset,
            up_mbit=args.up_mbit,
            down_mbit=args.down_mbit,
            delay_ms=args.delay_ms,
            jitter_ms=args.jitter_ms,
            loss_pct=args.loss_pct,
        )
    except ValueError as exc:
        raise SystemExit(f"netshape: {exc}") from None


def describe(link: netshape.Link) -> str:
    c = link.conditions
    return (
        f"link {link.name}: robot side {link.host_ip} (dev {link.robot_device}), cloud side {link.cloud_ip} "
        f"(netns {link.name}); up {c.up_mbit:g} Mbit/s, down {c.down_mbit:g} Mbit/s, delay {c.delay_ms:g} ms "
        f"+- {c.jitter_ms:g} ms, loss {c.loss_pct:g} %"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("presets", help="print the presets")
    for name in ("up", "run"):
        p = sub.add_parser(name, help="hold a link" if name == "up" else "run a command on the cloud side")
        p.add_argument("--preset", choices=sorted(netshape.PRESETS), default="wifi")
        p.add_argument("--up-mbit", type=float, help="robot -> cloud rate")
        p.add_argument("--down-mbit", type=float, help="cloud -> robot rate")
        p.add_argument("--delay-ms", type=float, help="one-way delay")
        p.add_argument("--jitter-ms", type=float, help="delay's standard deviation")
        p.add_argument("--loss-pct", type=float, help="packets lost each way, percent")
        p.add_argument("--name", help=f"link name ({netshape.PREFIX}ID; default random)")
        if name == "run":
            p.add_argument("cmd", nargs=argparse.REMAINDER, help="-- then the command")
    sub.add_parser("list", help="list bosuc- namespaces")
    p = sub.add_parser("clean", help="remove links whose owner is gone")
    p.add_argument("--all", action="store_true", help="remove every bosuc- link, owned or not")
    args = parser.parse_args(argv)

    if args.command == "presets":
        for name, preset in netshape.PRESETS.items():
            print(f"{name:5} {json.dumps(preset.as_dict())}")
        return 0
    if args.command == "list":
        for link in netshape.list_links():
            print(json.dumps(link))
        return 0
    if args.command == "clean":
        removed = netshape.clean(everything=args.all)
        print(f"removed {len(removed)} link(s){': ' + ', '.join(removed) if removed else ''}")
        return 0

    shaped = conditions(args)
    command = [c for c in getattr(args, "cmd", []) if c != "--"] if args.command == "run" else []
    if args.command == "run" and not command:
        parser.error("run needs a command after --")
    try:
        link = netshape.Link(shaped, name=args.name).up()
    except (RuntimeError, ValueError) as exc:
        print(f"netshape: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        print(describe(link), flush=True)
        if args.command == "run":
            env_note = {"NETSHAPE_HOST_IP": link.host_ip, "NETSHAPE_CLOUD_IP": link.cloud_ip}
            done = subprocess.run([*link.exec_prefix, "env", *(f"{k}={v}" for k, v in env_note.items()), *command])
            return done.returncode
        print("holding the link; Ctrl-C to remove it", flush=True)
        while not stop.wait(1.0):
            pass
        return 0
    finally:
        link.down()
        print(f"link {link.name} removed", flush=True)


if __name__ == "__main__":
    sys.exit(main())
