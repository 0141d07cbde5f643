"""Give every user who existed before organizations their personal one, where they are admin."""

from django.conf import settings
from django.db import migrations

from teams.naming import is_slug, personal_slug


def personal_organizations(apps, schema_editor):
    User = apps.get_model(*settings.AUTH_USER_MODEL.split("."))
    Organization = apps.get_model("teams", "Organization")
    Membership = apps.get_model("teams", "Membership")
    taken = set(Organization.objects.values_list("slug", flat=True))
    users = User.objects.order_by("pk").values_list("pk", "username")
    # A name that is a slug was its user's registry namespace: its owner takes it before another
    # name is fitted to it (a "Bob" who joined earlier would otherwise get bob's images).
    for user_id, username in sorted(users, key=lambda user: not is_slug(user[1])):
        if Organization.objects.filter(personal_of_id=user_id).exists():
            continue
        slug = personal_slug(username, user_id, taken.__contains__)
        taken.add(slug)
        organization = Organization.objects.create(slug=slug, name=username, personal_of_id=user_id)
        Membership.objects.create(organization=organization, user_id=user_id, role="admin")


class Migration(migrations.Migration):

    dependencies = [
        ("teams", "0001_initial"),
        migrations.swappable_dependency(settings.AUTH_USER_MODEL),
    ]

    operations = [migrations.RunPython(personal_organizations, migrations.RunPython.noop)]
