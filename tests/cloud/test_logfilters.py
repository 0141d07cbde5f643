"""The cloud's log: a robot offline or late is a warning; a fault of the cloud stays an error."""

from __future__ import annotations

import logging

import pytest
from django.http import HttpResponse
from django.test import RequestFactory
from django.utils.log import log_response


@pytest.mark.parametrize(("status", "level"), [(503, "WARNING"), (504, "WARNING"), (500, "ERROR"), (502, "ERROR")])
def test_answers_about_a_robots_state_are_warnings_and_faults_errors(status, level, caplog) -> None:
    request = RequestFactory().get("/api/robot/r1/skill/s/start")
    with caplog.at_level(logging.INFO, logger="django.request"):
        log_response("%s: %s", status, request.path, response=HttpResponse(status=status), request=request)
    (record,) = caplog.records
    assert record.levelname == level
