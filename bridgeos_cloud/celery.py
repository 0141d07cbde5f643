"""The Celery app: the cloud's workers that orchestrate containers and housekeeping."""

from __future__ import annotations

import os

from celery import Celery

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")

app = Celery("bridgeos_cloud")
app.config_from_object("django.conf:settings", namespace="CELERY")
app.autodiscover_tasks()
