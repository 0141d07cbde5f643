"""The Prometheus scrape door: /metrics, for allowed addresses or a bearer token."""

from __future__ import annotations

import hmac
import ipaddress
from functools import cache

from django.conf import settings
from django.http import HttpRequest, HttpResponse
from django.views.decorators.http import require_GET
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4

from . import prometheus


@cache
def _allowed_networks(cidrs: tuple[str, ...]) -> tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]:
    return tuple(ipaddress.ip_network(cidr, strict=False) for cidr in cidrs)


def may_scrape(request: HttpRequest) -> bool:
    """Tell whether the request carries the metrics token or comes from an allowed address."""
    token = settings.BRIDGEOS["METRICS_TOKEN"]
    header = request.headers.get("Authorization", "")
    if token and header.startswith("Bearer ") and hmac.compare_digest(header[7:].encode(), token.encode()):
        return True
    try:
        address = ipaddress.ip_address(request.META.get("REMOTE_ADDR", ""))
    except ValueError:
        return False
    return any(address in network for network in _allowed_networks(tuple(settings.BRIDGEOS["METRICS_ALLOW"])))


@require_GET
def metrics(request: HttpRequest) -> HttpResponse:
    """Serve the cloud's metrics in the Prometheus text format."""
    if not may_scrape(request):
        return HttpResponse(
            "metrics: send Authorization: Bearer <BRIDGEOS_METRICS_TOKEN> or scrape from BRIDGEOS_METRICS_ALLOW\n",
            status=403,
            content_type="text/plain",
        )
    # The 0.0.4 text format: what generate_latest writes and every Prometheus 2.x reads.
    return HttpResponse(prometheus.exposition(), content_type=CONTENT_TYPE_PLAIN_0_0_4)
