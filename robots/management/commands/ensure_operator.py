"""Make sure an operator account exists and print how to log in."""

from __future__ import annotations

import os
import secrets
from typing import Any

from django.conf import settings
from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand


class Command(BaseCommand):
    help = (
        "Create the operator superuser if missing (DJANGO_SUPERUSER_USERNAME/PASSWORD, "
        "default 'operator' with a generated password kept in the data dir) and print the login."
    )

    def handle(self, *args: Any, **options: Any) -> None:
        User = get_user_model()
        username = os.environ.get("DJANGO_SUPERUSER_USERNAME", "operator")
        password_file = settings.DATA_DIR / "operator-password"
        password = os.environ.get("DJANGO_SUPERUSER_PASSWORD")
        if password is None:
            if not password_file.exists():
                password_file.write_text(secrets.token_urlsafe(12))
                password_file.chmod(0o600)
            password = password_file.read_text().strip()
        user, created = User.objects.get_or_create(
            username=username, defaults={"is_staff": True, "is_superuser": True, "email": ""}
        )
        if created:
            user.set_password(password)
            user.save()
            self.stdout.write(f"Operator account created: {username} / {password}")
        elif user.check_password(password):
            self.stdout.write(f"Operator login: {username} / {password}")
        else:
            self.stdout.write(f"Operator account {username} exists (its password was changed by hand).")
