"""Allocate every robot a local and a cloud subnet and a tunnel address from the configured pools.

Allocations live in PostgreSQL (``Subnet``), where an exclusion constraint makes overlapping
networks impossible; allocations are serialised by a transaction-level advisory lock, so two
robots created at once never race for the same subnet. Rows cascade with their robot, so a
deleted robot's subnets are free again at once.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Sequence
from typing import Any

from django.conf import settings
from django.core.exceptions import ValidationError
from django.db import IntegrityError, connection, transaction

from monitoring.services import record_event
from robots.models import Robot

from .models import Subnet

__all__ = ["check_requested", "ensure_subnets", "first_free", "subnets"]

# pg_advisory_xact_lock key of IPAM ("bosn").
LOCK_KEY = 0x626F_736E
KINDS = ("local", "cloud")


def first_free(pools: Sequence[str], taken: Iterable[str], prefix: int) -> str | None:
    """Return the first network of size ``prefix`` inside the pools that overlaps nothing taken."""
    spans = sorted(
        (int(net.network_address), int(net.broadcast_address))
        for net in (ipaddress.ip_network(t, strict=False) for t in taken)
        if net.version == 4
    )
    size = 1 << (32 - prefix)
    for pool in pools:
        pool_net = ipaddress.ip_network(pool)
        start, end = int(pool_net.network_address), int(pool_net.broadcast_address)
        candidate = start
        for low, high in spans:
            if high < candidate or low > end:
                continue
            if low >= candidate + size:
                break  # the gap before this span holds the candidate
            # Skip past the span, to the next boundary of the wanted size.
            candidate = max(candidate, (high + size) // size * size)
            if candidate + size - 1 > end:
                break
        if candidate + size - 1 <= end:
            return str(ipaddress.ip_network((candidate, prefix)))
    return None


def _pools(kind: str) -> list[str]:
    return settings.BRIDGEOS_NETWORK["LOCAL_POOLS" if kind == "local" else "CLOUD_POOLS"]


def _lock() -> None:
    if connection.vendor == "postgresql":
        with connection.cursor() as cursor:
            cursor.execute("SELECT pg_advisory_xact_lock(%s)", [LOCK_KEY])


def check_requested(robot_id: str, config: dict[str, Any]) -> None:
    """Refuse subnets in a robot config that lie outside their pools or overlap another robot's."""
    requested = config.get("subnets") or {}
    if not requested:
        return
    own = dict(Subnet.objects.filter(robot_id=robot_id).values_list("kind", "network"))
    others = None
    for kind in KINDS:
        want = requested.get(kind)
        if not want or want == own.get(kind):
            continue  # unchanged: it was checked when it was allocated
        network = ipaddress.ip_network(want)
        pools = _pools(kind)
        if not any(network.version == 4 and network.subnet_of(ipaddress.ip_network(p)) for p in pools):
            message = f"subnets.{kind}: {want} is outside the {kind} pools ({', '.join(pools)})"
            raise ValidationError({"config": [message]})
        if others is None:
            others = list(Subnet.objects.exclude(robot_id=robot_id).values_list("robot_id", "network"))
        for other, taken in others:
            if network.overlaps(ipaddress.ip_network(taken)):
                raise ValidationError({"config": [f"subnets.{kind}: {want} overlaps {taken} of robot {other}"]})


def ensure_subnets(robot: Robot) -> dict[str, str]:
    """Make the robot's allocations match its config, allocating what is missing; return {kind: network}."""
    prefix = settings.BRIDGEOS_NETWORK["SUBNET_PREFIX"]
    requested = robot.config.get("subnets") or {}
    # Every cloud start asks: a robot whose allocations are all there and as configured needs no lock (the
    # one lock of all robots, which a burst of cloud starts would otherwise queue on).
    held = dict(Subnet.objects.filter(robot=robot).values_list("kind", "network"))
    if Subnet.Kind.TUNNEL in held and all(kind in held and requested.get(kind) in (None, held[kind]) for kind in KINDS):
        return {kind: held[kind] for kind in (*KINDS, "tunnel")}
    result: dict[str, str] = {}
    try:
        with transaction.atomic():
            _lock()
            rows = {row.kind: row for row in Subnet.objects.filter(robot=robot)}
            for kind in KINDS:
                want, row = requested.get(kind), rows.get(kind)
                if row is not None and want in (None, row.network):
                    result[kind] = row.network
                    continue
                if want is None:
                    taken = Subnet.objects.values_list("network", flat=True)
                    want = first_free(_pools(kind), taken, prefix)
                    if want is None:
                        raise ValidationError({"config": [f"subnets.{kind}: the {kind} pools are exhausted"]})
                else:
                    check_requested(robot.id, {"subnets": {kind: want}})
                if row is None:
                    Subnet.objects.create(robot=robot, kind=kind, network=want)
                else:
                    # A new robot's subnets come with its creation; a change is worth a line of its own.
                    record_event(
                        f"The {kind} subnet of robot {robot.id} moved from {row.network} to {want}",
                        robot_id=robot.id,
                        kind="robot_subnets",
                        data={"kind": kind, "from": row.network, kind: want},
                    )
                    row.network = want
                    row.save(update_fields=["network"])
                result[kind] = want
            if Subnet.Kind.TUNNEL not in rows:
                result["tunnel"] = _allocate_tunnel(robot)
            else:
                result["tunnel"] = rows[Subnet.Kind.TUNNEL].network
    except IntegrityError:
        # Only a writer that skipped the lock (another tool) can get here; the constraint held.
        raise ValidationError({"config": ["subnets: overlaps another robot's subnets"]}) from None
    return result


def _allocate_tunnel(robot: Robot) -> str:
    vpn = ipaddress.ip_network(settings.BRIDGEOS_NETWORK["VPN_NETWORK"])
    reserved = [f"{vpn.network_address}/32", f"{settings.BRIDGEOS_NETWORK['VPN_SERVER_IP']}/32"]
    reserved.append(f"{vpn.broadcast_address}/32")
    taken = [*Subnet.objects.filter(kind=Subnet.Kind.TUNNEL).values_list("network", flat=True), *reserved]
    address = first_free([str(vpn)], taken, 32)
    if address is None:
        raise ValidationError({"config": [f"the VPN network {vpn} has no address left"]})
    Subnet.objects.create(robot=robot, kind=Subnet.Kind.TUNNEL, network=address)
    return address


def subnets(robot: Robot) -> tuple[str, str]:
    """Return the robot's (local, cloud) subnets, allocating them if it has none yet."""
    allocated = ensure_subnets(robot)
    return allocated["local"], allocated["cloud"]
