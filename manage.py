#!/usr/bin/env python
"""Django's command-line utility for bridgeOS Cloud."""

from __future__ import annotations

import os
import sys


def main() -> None:
    """Run an administrative task."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    from django.core.management import execute_from_command_line

    execute_from_command_line(sys.argv)


if __name__ == "__main__":
    main()
