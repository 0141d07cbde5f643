"""The cloud's log: a robot offline or late is a warning; a fault of the cloud stays an error."""

from __future__ import annotations

import logging

import pytest
from django.http import HttpResponse
from django.test import RequestFactory
from django.utils.log import log_response


@pytest.mark.log_errors(r"django.request: 50[02]: ")  # a fault of the cloud stays an error: logged on purpose
@pytest.mark.parametrize(("status", "level"), [(503, "WARNING"), (504, "WARNING"), (500, "ERROR"), (502, "ERROR")])
def test_answers_about_a_robots_state_are_warnings_and_faults_errors(status, level, caplog) -> None:
    request = RequestFactory().get("/api/robot/r1/skill/s/start")
    with caplog.at_level(logging.INFO, logger="django.request"):
        log_response("%s: %s", status, request.path, response=HttpResponse(status=status), request=request)
    (record,) = caplog.records
    assert record.levelname == level


def test_a_request_django_refuses_as_suspicious_is_a_warning_without_a_traceback(client, caplog) -> None:
    """Too many fields: answered 400 with the reason; logged as a one-line warning, never an error."""
    with caplog.at_level(logging.INFO):
        response = client.get("/api/robot", {f"f{n}": "x" for n in range(1200)})
    assert response.status_code == 400
    suspicious = [r for r in caplog.records if r.name.startswith("django.security.")]
    assert suspicious and all(r.levelname == "WARNING" and r.exc_info is None for r in suspicious)
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
