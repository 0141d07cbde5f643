"""Render and run the cloud side of the VPN, its firewall, and the TLS certificate daphne serves."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser
from django.db import close_old_connections

from bridgeos_agent import firewall

from ... import services


class Command(BaseCommand):
    help = (
        "render DIR: write OpenVPN's server config, keys, CRL and a ccd entry per robot. "
        "run DIR: render, run openvpn, and keep ccd, CRL (and with --firewall the nftables rules) in step. "
        "firewall: apply the cloud's nftables rules when root, else print them. "
        "tls DIR: write the TLS certificate and key daphne serves (BRIDGEOS_TLS_CERT/KEY) and the CA."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        actions = parser.add_subparsers(dest="action", required=True)
        render = actions.add_parser("render")
        render.add_argument("directory", type=Path)
        run = actions.add_parser("run")
        run.add_argument("directory", type=Path)
        run.add_argument("--openvpn", default="openvpn", help="the openvpn program")
        run.add_argument("--interval", type=float, default=2.0, help="seconds between syncs (default 2)")
        run.add_argument("--firewall", action="store_true", help="also keep the nftables rules applied (root)")
        rules = actions.add_parser("firewall")
        rules.add_argument("--print", action="store_true", help="print the rules instead of applying them")
        tls = actions.add_parser("tls")
        tls.add_argument("directory", type=Path)

    def handle(self, *args: Any, action: str, **options: Any) -> None:
        getattr(self, f"do_{action}")(**options)

    def do_render(self, directory: Path, **options: Any) -> None:
        changed = services.write_files(directory, services.server_files())
        self.stdout.write(f"{directory}: {', '.join(changed) if changed else 'up to date'}")

    def do_firewall(self, print: bool = False, **options: Any) -> None:
        rules = services.firewall_rules()
        if print or not firewall.can_apply():
            self.stdout.write(rules)
            if not print:
                self.stderr.write("not root (or nft missing): rules printed, not applied")
            return
        try:
            firewall.apply_rules(rules)
        except firewall.FirewallError as exc:
            raise CommandError(str(exc)) from None
        self.stdout.write(f"cloud firewall applied (nft table inet {firewall.TABLE})")

    def do_tls(self, directory: Path, **options: Any) -> None:
        server = services.authority("tls-server")
        files = {
            "tls.crt": (server.cert_pem, 0o644),
            "tls.key": (server.key_pem, 0o600),
            "ca.crt": (services.authority("ca").cert_pem, 0o644),
        }
        services.write_files(directory, files)
        self.stdout.write(
            f"{directory}/tls.crt and tls.key: set BRIDGEOS_TLS_CERT and BRIDGEOS_TLS_KEY to them; "
            f"robots verify with {directory}/ca.crt (bridgeos-agent --ca) or the CA pinned in their config"
        )

    def do_run(self, directory: Path, openvpn: str, interval: float, firewall: bool, **options: Any) -> None:
        stopping = False

        def stop(signum: int, frame: Any) -> None:
            nonlocal stopping
            stopping = True

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
        self.do_render(directory)
        known, _ = services.revoked_robots_since(())
        rules = self._sync_firewall(None) if firewall else None
        log = (directory / "openvpn.log").open("ab")
        process = subprocess.Popen([openvpn, "--cd", str(directory), "--config", "server.conf"], stdout=log, stderr=log)
        self.stdout.write(f"openvpn running (pid {process.pid}, log {directory}/openvpn.log)")
        try:
            while not stopping and process.poll() is None:
                time.sleep(interval)
                close_old_connections()
                changed = services.write_files(directory, services.server_files())
                if changed:
                    self.stdout.write(f"updated {', '.join(changed)}")
                known, revoked = services.revoked_robots_since(known)
                for robot in sorted(revoked):
                    # The CRL refuses the next handshake; a live tunnel is cut now.
                    self._management(directory, f"kill {robot}")
                if firewall:
                    rules = self._sync_firewall(rules)
        finally:
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(15)
                except subprocess.TimeoutExpired:
                    process.kill()
            log.close()
        if not stopping:
            raise CommandError(f"openvpn exited with {process.returncode}; see {directory}/openvpn.log")

    def _sync_firewall(self, previous: str | None) -> str:
        rules = services.firewall_rules()
        if rules != previous:
            try:
                firewall.apply_rules(rules)
                self.stdout.write("cloud firewall applied")
            except firewall.FirewallError as exc:
                self.stderr.write(str(exc))
        return rules

    def _management(self, directory: Path, command: str) -> None:
        import socket

        # A unix socket path is limited to 108 bytes: reach a deep directory through its descriptor.
        fd = os.open(directory, os.O_RDONLY)
        try:
            with socket.socket(socket.AF_UNIX) as sock:
                sock.settimeout(5)
                sock.connect(f"/proc/self/fd/{fd}/management.sock")
                sock.sendall(command.encode() + b"\nquit\n")
                while sock.recv(4096):
                    pass
        except OSError as exc:
            self.stderr.write(f"management {command!r}: {exc}")
        else:
            self.stdout.write(f"management: {command}")
        finally:
            os.close(fd)
