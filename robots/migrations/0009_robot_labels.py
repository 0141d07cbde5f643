"""Add Robot.labels, with a GIN index where the database has them (PostgreSQL)."""

from __future__ import annotations

from django.db import migrations, models


def create_gin(apps, schema_editor):
    if schema_editor.connection.vendor == "postgresql":
        # jsonb_path_ops serves `labels @> '{...}'` (a selector's equalities) and is smaller than the default ops;
        # has_key terms need no index: they narrow a group the equalities or the organization already found.
        schema_editor.execute(
            "CREATE INDEX IF NOT EXISTS robot_labels_gin ON robots_robot USING gin (labels jsonb_path_ops)"
        )


def drop_gin(apps, schema_editor):
    if schema_editor.connection.vendor == "postgresql":
        schema_editor.execute("DROP INDEX IF EXISTS robot_labels_gin")


class Migration(migrations.Migration):
    dependencies = [("robots", "0008_robot_organization_required")]

    operations = [
        migrations.AddField(
            model_name="robot",
            name="labels",
            field=models.JSONField(
                blank=True, default=dict, help_text='key: value labels, e.g. {"site": "lab"}.'
            ),
        ),
        migrations.RunPython(create_gin, drop_gin),
    ]
