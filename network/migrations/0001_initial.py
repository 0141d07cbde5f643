from __future__ import annotations

import django.db.models.deletion
import django.utils.timezone
from django.db import migrations, models

import network.models

EXCLUDE = "ALTER TABLE network_subnet ADD CONSTRAINT subnet_no_overlap EXCLUDE USING gist (network inet_ops WITH &&)"


def add_exclusion(apps, schema_editor):
    # Overlapping allocations are impossible on PostgreSQL, whatever the application does.
    if schema_editor.connection.vendor == "postgresql":
        schema_editor.execute(EXCLUDE)


def drop_exclusion(apps, schema_editor):
    if schema_editor.connection.vendor == "postgresql":
        schema_editor.execute("ALTER TABLE network_subnet DROP CONSTRAINT subnet_no_overlap")


class Migration(migrations.Migration):
    initial = True

    dependencies = [("robots", "0004_robot_ros_master")]

    operations = [
        migrations.CreateModel(
            name="Authority",
            fields=[
                ("id", models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name="ID")),
                ("name", models.CharField(max_length=32, unique=True)),
                ("cert_pem", models.TextField(blank=True)),
                ("key_pem", models.TextField()),
                ("created_at", models.DateTimeField(default=django.utils.timezone.now, editable=False)),
            ],
            options={"verbose_name_plural": "authorities"},
        ),
        migrations.CreateModel(
            name="Revocation",
            fields=[
                ("id", models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name="ID")),
                ("serial", models.CharField(max_length=64, unique=True)),
                ("robot_id", models.CharField(max_length=64)),
                ("reason", models.CharField(max_length=200)),
                ("not_after", models.DateTimeField(help_text="Listed in the CRL until the certificate expires.")),
                ("revoked_at", models.DateTimeField(default=django.utils.timezone.now)),
            ],
            options={"ordering": ["revoked_at"]},
        ),
        migrations.CreateModel(
            name="ClientCertificate",
            fields=[
                ("id", models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name="ID")),
                ("serial", models.CharField(max_length=64, unique=True)),
                ("cert_pem", models.TextField()),
                ("key_pem", models.TextField()),
                ("not_after", models.DateTimeField()),
                ("created_at", models.DateTimeField(default=django.utils.timezone.now, editable=False)),
                (
                    "robot",
                    models.OneToOneField(
                        on_delete=django.db.models.deletion.CASCADE, related_name="vpn_certificate", to="robots.robot"
                    ),
                ),
            ],
        ),
        migrations.CreateModel(
            name="Subnet",
            fields=[
                ("id", models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name="ID")),
                (
                    "kind",
                    models.CharField(
                        choices=[
                            ("local", "local (the robot's container network)"),
                            ("cloud", "cloud (the robot's cloud container network)"),
                            ("tunnel", "tunnel (the robot's VPN address)"),
                        ],
                        max_length=8,
                    ),
                ),
                ("network", network.models.CidrField(max_length=43, unique=True)),
                ("created_at", models.DateTimeField(default=django.utils.timezone.now, editable=False)),
                (
                    "robot",
                    models.ForeignKey(
                        on_delete=django.db.models.deletion.CASCADE, related_name="subnets", to="robots.robot"
                    ),
                ),
            ],
            options={
                "ordering": ["robot_id", "kind"],
                "constraints": [models.UniqueConstraint(fields=("robot", "kind"), name="subnet_one_per_kind")],
            },
        ),
        migrations.RunPython(add_exclusion, drop_exclusion),
    ]
