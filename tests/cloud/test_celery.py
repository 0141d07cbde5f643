"""A Celery task round-trips through a real worker on Redis."""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.contrib.auth import get_user_model
from django.utils import timezone

from monitoring.models import Metric
from monitoring.tasks import prune_metrics
from robots.services import create_robot

pytestmark = pytest.mark.django_db(transaction=True)


def test_prune_metrics_runs_on_a_real_worker(celery_worker_process):
    owner = get_user_model().objects.create_user("owner")
    robot, _ = create_robot("r1", owner)
    now = timezone.now()
    Metric.objects.bulk_create(
        [Metric(robot=robot, name="cpu", value=i, ts=now - timedelta(days=i)) for i in range(10)]
    )

    result = prune_metrics.delay(older_than_seconds=timedelta(days=4, hours=12).total_seconds())

    assert result.get(timeout=30) == 5
    assert sorted(Metric.objects.values_list("value", flat=True)) == [0, 1, 2, 3, 4]
    assert "prune_metrics" in celery_worker_process.read_text()
