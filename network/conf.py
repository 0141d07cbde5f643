"""The network settings, read from the environment (imported by bridgeos_cloud.settings)."""

from __future__ import annotations

import ipaddress
from typing import Any

from bridgeos_cloud.env import ConfigError, env_int, env_list, env_str


def _networks(name: str, values: list[str]) -> list[str]:
    checked = []
    for value in values:
        try:
            network = ipaddress.ip_network(value, strict=True)
        except ValueError as exc:
            raise ConfigError(f"{name}: {value!r} is not a network in CIDR notation ({exc})") from None
        if network.version != 4:
            raise ConfigError(f"{name}: {value} is IPv6; the VPN routes IPv4 only")
        checked.append(str(network))
    return checked


def network_settings() -> dict[str, Any]:
    """Return the IPAM pools, VPN and TLS settings, checked so no two of the networks overlap."""
    local = _networks("BRIDGEOS_LOCAL_POOLS", env_list("BRIDGEOS_LOCAL_POOLS", ["10.64.0.0/12"]))
    cloud = _networks("BRIDGEOS_CLOUD_POOLS", env_list("BRIDGEOS_CLOUD_POOLS", ["10.80.0.0/12"]))
    vpn = _networks("BRIDGEOS_VPN_NETWORK", [env_str("BRIDGEOS_VPN_NETWORK", "10.8.0.0/16") or ""])[0]
    prefix = env_int("BRIDGEOS_SUBNET_PREFIX", 24)
    everything = [(name, ipaddress.ip_network(n)) for name, ns in (("local", local), ("cloud", cloud)) for n in ns]
    everything.append(("vpn", ipaddress.ip_network(vpn)))
    for i, (name_a, a) in enumerate(everything):
        for name_b, b in everything[i + 1 :]:
            if a.overlaps(b):
                raise ConfigError(f"the {name_a} network {a} overlaps the {name_b} network {b}: make them disjoint")
    if not all(ipaddress.ip_network(n).prefixlen <= prefix <= 30 for n in local + cloud):
        raise ConfigError(f"BRIDGEOS_SUBNET_PREFIX={prefix} must be at most 30 and no shorter than every pool's")
    tls_port = env_int("BRIDGEOS_TLS_PORT", 8443)
    server_ip = str(next(ipaddress.ip_network(vpn).hosts()))
    return {
        "LOCAL_POOLS": local,
        "CLOUD_POOLS": cloud,
        "SUBNET_PREFIX": prefix,
        "VPN_NETWORK": vpn,
        "VPN_SERVER_IP": server_ip,
        # host:port robots dial; without it the cloud serves no VPN profiles.
        "VPN_REMOTES": env_list("BRIDGEOS_VPN_REMOTE", []),
        "VPN_PROTO": env_str("BRIDGEOS_VPN_PROTO", "udp"),
        "VPN_PORT": env_int("BRIDGEOS_VPN_PORT", 1194),
        "VPN_DEVICE": env_str("BRIDGEOS_VPN_DEVICE", "bridgeos-vpn"),
        # The cloud's WebSocket URL inside the tunnel, sent to robots in their config.
        "VPN_MASTER": env_str("BRIDGEOS_VPN_MASTER", "") or f"wss://{server_ip}:{tls_port}",
        "TLS_PORT": tls_port,
        # Names and addresses the PKI's TLS certificate carries (the VPN address is always added).
        "TLS_NAMES": env_list("BRIDGEOS_TLS_NAMES", ["localhost", "127.0.0.1"]),
        # Pin the cloud CA in robots' configs (set when daphne serves a certificate of this PKI).
        "PIN_CA": env_str("BRIDGEOS_PIN_CA", "") not in ("", "0", "false", "no"),
    }
