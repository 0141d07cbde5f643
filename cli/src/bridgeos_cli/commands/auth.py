"""`bridgeos login`, `logout` and `whoami`."""

from __future__ import annotations

import click

from .. import config
from ..output import emit_json, fields, json_option, state


@click.command()
@click.argument("url")
@click.option("-u", "--username", help="Your username on the cloud (asked when not given).")
@click.option(
    "--password",
    envvar="BRIDGEOS_PASSWORD",
    help="Your password (asked, hidden, when not given; also from BRIDGEOS_PASSWORD).",
)
@click.option("--token", help="An API token made on the cloud (e.g. a scoped one for CI) instead of a password.")
@json_option
def login(url: str, username: str | None, password: str | None, token: str | None) -> None:
    """Log in to the cloud at URL and keep an API token for the next commands.

    With a username and password the cloud's /api/auth issues a token (valid a
    day by default); with --token that token is checked and kept as it is.

    \b
    Examples:
      bridgeos login https://cloud.example.com
      bridgeos login http://127.0.0.1:8000 -u operator
      bridgeos login https://cloud.example.com --token "$CI_BRIDGEOS_TOKEN"
    """
    from ..client import Api, fetch_token

    base = config.normalise_url(url)
    if token:
        login = config.Login(base, token, username)
        api = Api(login)
        try:
            # Any read proves the token: the smallest page of the fleet.
            api.get("/api/robot", limit=1, fields="id")
        finally:
            api.close()
    else:
        if username is None:
            username = click.prompt("Username", err=True)
        if password is None:
            password = click.prompt("Password", hide_input=True, err=True)
        answer = fetch_token(base, username, password)
        login = config.Login(base, answer["token"], username, answer.get("expires_at"))
    path = config.save(login)
    if state().json:
        emit_json({"url": login.url, "username": login.username, "expires_at": login.expires_at, "config": str(path)})
        return
    who = f" as {login.username}" if login.username else ""
    until = f" (token valid until {login.expires_at})" if login.expires_at else ""
    click.echo(f"Logged in to {login.url}{who}{until}.")
    click.echo(f"Login kept in {path}.", err=True)


@click.command()
def logout() -> None:
    """Forget the stored URL and token (the token itself expires on the cloud).

    \b
    Example:
      bridgeos logout
    """
    if config.forget():
        click.echo(f"Logged out: {config.config_path()} removed.")
    else:
        click.echo("Not logged in: nothing to forget.")


@click.command()
@json_option
def whoami() -> None:
    """Show the cloud and user this command line acts for, and check the token still works.

    \b
    Examples:
      bridgeos whoami
      BRIDGEOS_URL=http://127.0.0.1:8000 BRIDGEOS_TOKEN=... bridgeos whoami --json
    """
    api = state().api()
    robots = api.get("/api/robot", limit=1, fields="id")
    login = api.login
    data = {"url": login.url, "username": login.username, "expires_at": login.expires_at, "robots": robots["count"]}
    if state().json:
        emit_json(data)
    else:
        fields(data)
