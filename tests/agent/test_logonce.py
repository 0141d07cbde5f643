"""LogOnce: a failure repeated every tick is said once per distinct error."""

from __future__ import annotations

import logging

import pytest

from bridgeos_agent.logonce import LogOnce


def test_the_same_error_is_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    said = LogOnce(logging.getLogger("test.logonce"), "measuring")
    with caplog.at_level(logging.INFO, logger="test.logonce"):
        results = [said.failed(OSError("docker is down")) for _ in range(5)]
    assert results == [True, False, False, False, False]
    assert [r.getMessage() for r in caplog.records] == [
        "measuring failed: OSError: docker is down (said once until it works again)"
    ]


def test_a_different_error_is_logged_too() -> None:
    said = LogOnce(logging.getLogger("test.logonce"), "measuring")
    assert said.failed(OSError("docker is down"))
    assert said.failed(TimeoutError("slow"))
    assert not said.failed(OSError("docker is down"))


def test_after_it_works_again_the_error_is_logged_again(caplog: pytest.LogCaptureFixture) -> None:
    said = LogOnce(logging.getLogger("test.logonce"), "measuring")
    said.failed(OSError("docker is down"))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="test.logonce"):
        said.worked()
        said.worked()
    assert [r.getMessage() for r in caplog.records] == ["measuring works again"]
    assert said.failed(OSError("docker is down"))
