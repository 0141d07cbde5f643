"""Create a robot and print its token once."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError
from django.core.management.base import BaseCommand, CommandError, CommandParser

from robots.services import create_robot


class Command(BaseCommand):
    help = "Create a robot owned by USERNAME and print its token (shown only this once) on stdout."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("robot_id", help="Slug id of the robot: lowercase letters, digits, '-' or '_'.")
        parser.add_argument("--owner", required=True, help="Username of the robot's owner.")
        parser.add_argument("--name", default="", help="Human-readable name.")
        parser.add_argument("--config", type=Path, help="JSON file with the robot config (default: defaults).")

    def handle(self, *args: Any, **options: Any) -> None:
        User = get_user_model()
        try:
            owner = User.objects.get(username=options["owner"])
        except User.DoesNotExist:
            raise CommandError(f"No user named {options['owner']!r}; create it first (createsuperuser).") from None
        config = None
        if options["config"] is not None:
            try:
                config = json.loads(options["config"].read_text())
            except (OSError, ValueError) as exc:
                raise CommandError(f"Cannot read robot config {options['config']}: {exc}") from None
        try:
            _, token = create_robot(options["robot_id"], owner, name=options["name"], config=config)
        except ValidationError as exc:
            raise CommandError(_describe(exc)) from None
        self.stderr.write(f"Robot {options['robot_id']} created for {owner}. Its token is shown only once:")
        self.stdout.write(token)


def _describe(exc: ValidationError) -> str:
    """Render field errors as 'field: message' lines."""
    if hasattr(exc, "message_dict"):
        return "; ".join(f"{field}: {msg}" for field, msgs in exc.message_dict.items() for msg in msgs)
    return "; ".join(exc.messages)
