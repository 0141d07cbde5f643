"""`bridgeos images`: the repositories of the cloud's registry you may pull, with their tags."""

from __future__ import annotations

import click

from ..output import json_option, show, state, table

COLUMNS = ["repository", "tag", "digest", "size", "pushed_by", "pushed_at"]


@click.group()
def images() -> None:
    """List the images in the cloud's registry."""


@images.command("ls")
@click.option("--namespace", help="Only this namespace (an organization's slug, or your username).")
@json_option
def images_ls(namespace: str | None) -> None:
    """List repositories and their tags with each tag's digest.

    \b
    Examples:
      bridgeos images ls
      bridgeos images ls --namespace lab --json | jq -r '.[].repository'
    """
    found = state().api().get("/api/registry/repositories", namespace=namespace)

    def render(repositories: list[dict]) -> None:
        rows = [{"repository": repo["repository"], **tag} for repo in repositories for tag in repo["tags"]]
        table(rows, COLUMNS, empty="No images.")

    show(found, render)
