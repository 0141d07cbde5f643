"""The log guard fails a test whose logs hold an unexpected error, and lets through what a test marks."""

from __future__ import annotations

import textwrap

import pytest

from tests.conftest import ROOT
from tests.logguard import bad_entries

pytest_plugins = ["pytester"]

CLOUD_LOG = """\
2026-12-02 04:05:24,074 INFO daphne.server: listening
2026-12-02 04:05:24,075 ERROR robots.consumers: robot r-1: frame failed
Traceback (most recent call last):
  File "robots/consumers.py", line 10, in dispatch_envelope
    handler = HANDLERS[envelope.event]
KeyError: 'components_api_reply'
2026-12-02 04:05:24,076 INFO daphne.server: robot r-1 connected
[2026-12-02 04:05:25,000: ERROR/MainProcess] Task skills.tasks.launch raised: boom
2026-12-02 04:05:25,001 WARNING django.request: Service Unavailable: /api/robot/r-1/info
"""


def test_an_error_line_carries_its_traceback_and_stops_at_the_next_record() -> None:
    entries = bad_entries(CLOUD_LOG)
    assert len(entries) == 2
    assert entries[0].splitlines()[0].endswith("frame failed")
    assert entries[0].splitlines()[-1] == "KeyError: 'components_api_reply'"
    assert entries[1] == "[2026-12-02 04:05:25,000: ERROR/MainProcess] Task skills.tasks.launch raised: boom"


def test_the_registrys_logrus_error_lines_are_errors_and_its_warnings_are_not() -> None:
    log = (
        'time="2026-12-02T06:49:31Z" level=warning msg="error authorizing context: invalid token"\n'
        'time="2026-12-02T06:49:31Z" level=error msg="response completed with error" err.code="blob unknown"\n'
        'time="2026-12-02T06:49:32Z" level=info msg="response completed"\n'
    )
    assert bad_entries(log) == [
        'time="2026-12-02T06:49:31Z" level=error msg="response completed with error" err.code="blob unknown"'
    ]


def test_a_request_line_of_an_access_log_is_never_an_error_whatever_its_url_says() -> None:
    access = '127.0.0.1:54916 - - [02/Dec/2026:07:16:47] "GET /api/events?level=error&kind=ERROR" 400 436'
    assert bad_entries(access + "\n") == []
    # Nor does it carry on an error entry before it.
    assert bad_entries("2026-12-02 04:05:24,075 ERROR a: b\n" + access + "\n") == ["2026-12-02 04:05:24,075 ERROR a: b"]


def test_info_and_warning_lines_are_not_errors() -> None:
    assert bad_entries("2026-12-02 04:05:24,074 INFO x: the word error in lower case\nWARNING y: late\n") == []


@pytest.fixture
def guarded(pytester: pytest.Pytester) -> pytest.Pytester:
    pytester.makeconftest("")
    pytester.makepyfile(
        test_guarded=textwrap.dedent(
            """
            import logging
            import pytest
            from tests.logguard import watch

            def test_logs_an_error():
                logging.getLogger("bridgeos_agent").error("robot r-1: the link broke")

            @pytest.mark.log_errors(r"the link broke")
            def test_provokes_it_on_purpose():
                logging.getLogger("bridgeos_agent").error("robot r-1: the link broke")

            @pytest.mark.log_errors(r"the link broke")
            def test_provokes_another_than_it_says():
                logging.getLogger("bridgeos_agent").error("robot r-1: the disk is full")

            def test_a_watched_log_holds_a_traceback(tmp_path):
                log = watch(tmp_path / "daphne.log")
                log.write_text("2026-12-02 04:05:24,074 INFO a: ok\\nTraceback (most recent call last):\\n"
                               "  File 'x', line 1\\nKeyError: 'id'\\n")

            def test_a_watched_log_written_before_it_was_watched_is_not_read(tmp_path):
                log = tmp_path / "daphne.log"
                log.write_text("ERROR old: before\\n")
                watch(log)

            def test_warnings_pass():
                logging.getLogger("bridgeos_agent").warning("robot r-1: slow")
            """
        )
    )
    return pytester


def test_the_guard_fails_exactly_the_tests_with_unexpected_errors(
    guarded: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    result = guarded.runpytest_subprocess("-p", "tests.logguard", "-p", "no:cacheprovider", "-rE")
    result.assert_outcomes(passed=6, errors=3)
    failed = {line.split("::")[1].split()[0] for line in result.outlines if line.startswith("ERROR test_guarded.py")}
    assert failed == {
        "test_logs_an_error",
        "test_provokes_another_than_it_says",
        "test_a_watched_log_holds_a_traceback",
    }
    assert "the disk is full" in result.stdout.str() and "KeyError: 'id'" in result.stdout.str()
