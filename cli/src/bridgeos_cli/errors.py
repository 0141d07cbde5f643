"""What can go wrong, each with the exit code that says so (docs/operators/cli.md lists them)."""

from __future__ import annotations

from typing import Any

import click

OK = 0
API_ERROR = 1  # the cloud refused the request (400, 403, 409, 5xx...)
USAGE = 2  # click's own code for a bad command line
AUTH = 3  # not logged in, or the cloud refused the credentials (401)
NOT_FOUND = 4  # no such robot, Skill, component, recording... (or not yours: 404)
CONNECTION = 5  # the cloud could not be reached, or did not answer in time


class CliError(click.ClickException):
    """An error shown as ``Error: message`` on stderr, ending the command with its exit code."""

    def __init__(self, message: str, exit_code: int = API_ERROR) -> None:
        super().__init__(message)
        # click reads the code off the instance; its stubs declare the class's default a ClassVar.
        self.exit_code = exit_code  # type: ignore[misc]


class NotLoggedIn(CliError):
    """No cloud URL or token: neither `bridgeos login` nor BRIDGEOS_URL/BRIDGEOS_TOKEN."""

    def __init__(
        self, message: str = "Not logged in: run `bridgeos login URL` (or set BRIDGEOS_URL and BRIDGEOS_TOKEN)."
    ) -> None:
        super().__init__(message, AUTH)


def api_message(body: Any) -> str:
    """Word an API error body as the API does: its detail, or each field with its messages."""
    if isinstance(body, dict):
        if set(body) == {"detail"}:
            return str(body["detail"])
        parts = []
        for field, messages in body.items():
            if isinstance(messages, list):
                text = "; ".join(
                    api_message(message) if isinstance(message, dict) else str(message) for message in messages
                )
            elif isinstance(messages, dict):
                text = api_message(messages)
            else:
                text = str(messages)
            parts.append(text if field in ("detail", "non_field_errors") else f"{field}: {text}")
        return "\n".join(parts)
    if isinstance(body, list):
        return "\n".join(api_message(item) for item in body)
    return str(body)


def exit_code_for(status: int) -> int:
    """Return the exit code of an HTTP error status."""
    if status == 401:
        return AUTH
    if status == 404:
        return NOT_FOUND
    # A 409 (robot offline) or 504 (robot did not answer) is the cloud's answer, not a broken link.
    return API_ERROR
