"""Add a BRIN index on Metric.ts where the database has them (PostgreSQL)."""

from __future__ import annotations

from django.db import migrations


def create_brin(apps, schema_editor):
    if schema_editor.connection.vendor == "postgresql":
        # Metric rows arrive in time order, so a BRIN index answers time ranges at a tiny size.
        schema_editor.execute(
            "CREATE INDEX IF NOT EXISTS metric_ts_brin ON monitoring_metric USING brin (ts) WITH (pages_per_range = 32)"
        )


def drop_brin(apps, schema_editor):
    if schema_editor.connection.vendor == "postgresql":
        schema_editor.execute("DROP INDEX IF EXISTS metric_ts_brin")


class Migration(migrations.Migration):
    dependencies = [("monitoring", "0001_initial")]
    operations = [migrations.RunPython(create_brin, drop_brin)]
