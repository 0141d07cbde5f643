"""A Skill Router's totals turned into the delivered and dropped rates a robot reports for its rollout gates."""

from __future__ import annotations

from typing import Any

from bridgeos_agent.delivery import ROUTER_DELIVERED, ROUTER_DROPPED, DeliveryRates, delivery_totals


class Counted:
    """A router's statistics as RouterStatistics.statistics() returns them, set by the test."""

    def __init__(self) -> None:
        self.figures: dict[str, dict[str, Any]] = {}

    def statistics(self) -> dict[str, dict[str, Any]]:
        return self.figures

    def route(self, delivered: int, dropped: int, calls: int = 0, errors: int = 0) -> None:
        self.figures = {
            "/scan": {"kind": "topic", "delivered": delivered, "dropped": dropped, "messages": delivered + dropped},
            "/plan": {"kind": "service", "calls": calls, "errors": errors, "bytes": 0},
        }


def test_totals_count_topics_deliveries_and_drops_and_services_calls_and_errors():
    router = Counted()
    router.route(delivered=90, dropped=10, calls=5, errors=2)
    assert delivery_totals(router.statistics()) == (93, 12)
    assert delivery_totals({}) == (0, 0)


def test_rates_come_from_the_difference_between_samples_and_a_new_router_starts_again():
    rates, router = DeliveryRates(), Counted()
    router.route(delivered=100, dropped=0)
    assert rates.sample([("nav", router)], now=10.0) == []  # the first sample is the baseline
    router.route(delivered=300, dropped=50)
    assert rates.sample([("nav", router)], now=12.0) == [
        (ROUTER_DELIVERED, 100.0, "nav", None),
        (ROUTER_DROPPED, 25.0, "nav", None),
    ]
    # The Skill restarted (a release installed): its new router's totals start from zero, not negative.
    fresh = Counted()
    fresh.route(delivered=5, dropped=0)
    assert rates.sample([("nav", fresh)], now=13.0) == []
    fresh.route(delivered=15, dropped=0)
    assert rates.sample([("nav", fresh)], now=14.0) == [
        (ROUTER_DELIVERED, 10.0, "nav", None),
        (ROUTER_DROPPED, 0.0, "nav", None),
    ]
    # A Skill gone is forgotten: when it comes back, its first sample is a baseline again.
    assert rates.sample([], now=15.0) == []
    assert rates.sample([("nav", fresh)], now=16.0) == []
