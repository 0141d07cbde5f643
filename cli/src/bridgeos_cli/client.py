"""The HTTP side: one httpx client per command, API errors turned into CLI errors with their exit codes."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from . import config
from .errors import AUTH, CONNECTION, CliError, api_message, exit_code_for

if TYPE_CHECKING:
    import httpx

TIMEOUT_S = 30.0
# A command waits for the robot's answer up to ?wait= seconds: the HTTP request must outlast it.
COMMAND_SLACK_S = 15.0
MAX_PAGE = 1000  # the largest page the API's lists serve


def user_agent() -> str:
    from . import __version__

    return f"bridgeos-cli/{__version__}"


def raise_for(response: httpx.Response) -> None:
    """Raise a CliError worded as the API words it when the response is an error."""
    if response.is_success:
        return
    try:
        body: Any = response.json()
    except ValueError:
        # Not the API's JSON (a proxy's page, a wrong URL): say the status and where, not the page.
        body = f"HTTP {response.status_code} {response.reason_phrase} from {response.request.url}"
    message = api_message(body)
    if response.status_code == 401:
        message = f"{message}\nThe cloud refused the credentials: run `bridgeos login` again."
    raise CliError(message or f"HTTP {response.status_code}", exit_code_for(response.status_code))


@contextmanager
def connection_errors(url: str) -> Iterator[None]:
    """Turn a failure to reach the cloud into exit code 5, saying which URL."""
    import httpx

    try:
        yield
    except httpx.TimeoutException:
        raise CliError(f"The cloud at {url} did not answer in time.", CONNECTION) from None
    except httpx.TransportError as exc:
        raise CliError(f"Cannot reach the cloud at {url}: {exc}", CONNECTION) from None


class Api:
    """The Robot API of one cloud, authenticated with the login's token."""

    def __init__(self, login: config.Login) -> None:
        import httpx

        self.login = login
        self.http = httpx.Client(
            base_url=login.url,
            headers={"Authorization": f"Token {login.token}", "User-Agent": user_agent()},
            timeout=TIMEOUT_S,
        )

    def request(self, method: str, path: str, *, timeout: float | None = None, **kwargs: Any) -> httpx.Response:
        """Send a request and return its successful response; raise a CliError otherwise."""
        with connection_errors(self.login.url):
            response = self.http.request(method, path, timeout=timeout or TIMEOUT_S, **kwargs)
        raise_for(response)
        return response

    def get(self, path: str, **params: Any) -> Any:
        """GET a JSON answer; parameters that are None are left out."""
        return self.request("GET", path, params={k: v for k, v in params.items() if v is not None}).json()

    def post(self, path: str, body: Any = None, *, wait: float | None = None) -> Any:
        """POST JSON and return the JSON answer (None for 204); ``wait`` goes as ?wait= seconds."""
        params = {"wait": wait} if wait is not None else {}
        timeout = (wait or 5.0) + COMMAND_SLACK_S
        response = self.request("POST", path, json=body, params=params, timeout=timeout)
        return None if response.status_code == 204 or not response.content else response.json()

    def pages(self, path: str, *, limit: int | None = None, **params: Any) -> Iterator[dict]:
        """Yield the results of a paginated list ({count, next, results}) until ``limit`` or the end."""
        shown = 0
        first = {k: v for k, v in params.items() if v is not None}
        if limit is not None:
            first["limit"] = min(limit, MAX_PAGE)
        query: dict[str, Any] | None = first
        url = path
        while url:
            body = self.request("GET", url, params=query).json()
            if isinstance(body, list):
                # An unpaginated list is the whole answer.
                yield from body[:limit] if limit is not None else body
                return
            for item in body["results"]:
                yield item
                shown += 1
                if limit is not None and shown >= limit:
                    return
            url, query = body.get("next"), None

    @contextmanager
    def stream(self, path: str) -> Iterator[httpx.Response]:
        """Open a streamed GET (a download), raising a CliError on an error status."""
        with connection_errors(self.login.url), self.http.stream("GET", path, timeout=TIMEOUT_S) as response:
            if not response.is_success:
                response.read()
                raise_for(response)
            yield response

    def close(self) -> None:
        self.http.close()


def fetch_token(url: str, username: str, password: str) -> dict:
    """Exchange a username and password for an API token at /api/auth (HTTP Basic)."""
    import httpx

    with connection_errors(url):
        response = httpx.post(
            f"{url}/api/auth", auth=(username, password), headers={"User-Agent": user_agent()}, timeout=TIMEOUT_S
        )
    if response.status_code in (401, 403):
        try:
            detail = api_message(response.json())
        except ValueError:
            detail = response.reason_phrase
        raise CliError(f"Login refused: {detail}", AUTH)
    raise_for(response)
    return response.json()
