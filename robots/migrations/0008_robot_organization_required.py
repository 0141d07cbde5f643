import django.db.models.deletion
from django.db import migrations, models


class Migration(migrations.Migration):

    dependencies = [("robots", "0007_organizations")]

    operations = [
        migrations.AlterField(
            model_name="robot",
            name="organization",
            field=models.ForeignKey(
                on_delete=django.db.models.deletion.CASCADE, related_name="robots", to="teams.organization"
            ),
        ),
        migrations.RemoveIndex(model_name="robot", name="robots_robo_owner_i_f3b718_idx"),
        migrations.AddIndex(
            model_name="robot", index=models.Index(fields=["organization", "id"], name="robot_organization_id")
        ),
    ]
