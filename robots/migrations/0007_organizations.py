"""Robots belong to an organization: each existing robot to its owner's personal one; robot tokens rotate with overlap; API tokens get a name, a scope and an optional expiry."""

import django.db.models.deletion
from django.conf import settings
from django.db import migrations, models


def robots_to_personal_organizations(apps, schema_editor):
    Robot = apps.get_model("robots", "Robot")
    Organization = apps.get_model("teams", "Organization")
    for owner_id, organization_id in Organization.objects.exclude(personal_of=None).values_list("personal_of_id", "id"):
        Robot.objects.filter(owner_id=owner_id, organization=None).update(organization_id=organization_id)


class Migration(migrations.Migration):

    dependencies = [
        ("robots", "0006_bridge_ticket"),
        ("teams", "0002_personal_organizations"),
        migrations.swappable_dependency(settings.AUTH_USER_MODEL),
    ]

    operations = [
        migrations.AddField(
            model_name="robot",
            name="organization",
            field=models.ForeignKey(
                null=True, on_delete=django.db.models.deletion.CASCADE, related_name="robots", to="teams.organization"
            ),
        ),
        migrations.AlterField(
            model_name="robot",
            name="owner",
            field=models.ForeignKey(
                blank=True,
                null=True,
                on_delete=django.db.models.deletion.SET_NULL,
                related_name="robots",
                to=settings.AUTH_USER_MODEL,
            ),
        ),
        migrations.AddField(
            model_name="robot",
            name="previous_token_hash",
            field=models.CharField(blank=True, editable=False, max_length=64),
        ),
        migrations.AddField(
            model_name="robot",
            name="previous_token_until",
            field=models.DateTimeField(blank=True, editable=False, null=True),
        ),
        migrations.AddField(model_name="apitoken", name="name", field=models.CharField(blank=True, max_length=100)),
        migrations.AddField(
            model_name="apitoken",
            name="organization",
            field=models.ForeignKey(
                blank=True,
                null=True,
                on_delete=django.db.models.deletion.CASCADE,
                related_name="api_tokens",
                to="teams.organization",
            ),
        ),
        migrations.AddField(model_name="apitoken", name="role", field=models.CharField(blank=True, max_length=16)),
        migrations.AlterField(
            model_name="apitoken",
            name="expires_at",
            field=models.DateTimeField(blank=True, help_text="None: until revoked.", null=True),
        ),
        migrations.RunPython(robots_to_personal_organizations, migrations.RunPython.noop),
    ]
