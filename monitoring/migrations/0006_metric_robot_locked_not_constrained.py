"""Metric rows lose their foreign key to robots: ingest locks a batch's robots, a deletion its robot.

PostgreSQL checked the key row by row, 40 % of what storing a point cost. `monitoring.sinks` and
`robots.receivers` keep the same guarantee: no point outlives its robot.
"""

import django.db.models.deletion
from django.db import migrations, models


class Migration(migrations.Migration):
    dependencies = [
        ("monitoring", "0005_metric_partitioned_by_day"),
        ("robots", "0009_robot_labels"),
    ]

    operations = [
        migrations.AlterField(
            model_name="metric",
            name="robot",
            field=models.ForeignKey(
                db_constraint=False,
                db_index=False,
                on_delete=django.db.models.deletion.CASCADE,
                related_name="metrics",
                to="robots.robot",
            ),
        ),
    ]
