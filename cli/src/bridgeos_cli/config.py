"""Where the CLI keeps the cloud's URL and its API token: a JSON file only its user may read."""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

from .errors import NotLoggedIn

URL_ENV = "BRIDGEOS_URL"
TOKEN_ENV = "BRIDGEOS_TOKEN"


def config_path() -> Path:
    """Return $XDG_CONFIG_HOME/bridgeos/config.json, or ~/.config/bridgeos/config.json."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "bridgeos" / "config.json"


@dataclass
class Login:
    """A cloud and the API token the CLI presents to it."""

    url: str
    token: str
    username: str | None = None
    expires_at: str | None = None


def normalise_url(url: str) -> str:
    """Return the cloud's base URL: http(s) scheme, no trailing slash, no /api suffix."""
    url = url.strip().rstrip("/")
    if "://" not in url:
        url = "http://" + url
    return url.removesuffix("/api")


def read_file() -> dict:
    """Return the stored login, or {} when there is none (or it is unreadable)."""
    try:
        data = json.loads(config_path().read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def current() -> Login:
    """Return the login to use: BRIDGEOS_URL/BRIDGEOS_TOKEN over the stored one; NotLoggedIn without either."""
    stored = read_file()
    url = os.environ.get(URL_ENV) or stored.get("url")
    token = os.environ.get(TOKEN_ENV) or stored.get("token")
    if not url or not token:
        raise NotLoggedIn()
    return Login(normalise_url(url), token, stored.get("username"), stored.get("expires_at"))


def save(login: Login) -> Path:
    """Write the login, readable and writable by its user alone (mode 600, directory 700)."""
    path = config_path()
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    text = json.dumps(
        {"url": login.url, "token": login.token, "username": login.username, "expires_at": login.expires_at}, indent=2
    )
    temporary = path.with_suffix(".tmp")
    with contextlib.suppress(FileNotFoundError):
        temporary.unlink()
    # Created with mode 600 from the start: the token is never readable by others, not even briefly.
    descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as out:
        out.write(text + "\n")
    os.replace(temporary, path)
    return path


def forget() -> bool:
    """Delete the stored login; return whether there was one."""
    try:
        config_path().unlink()
    except FileNotFoundError:
        return False
    return True
