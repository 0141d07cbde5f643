"""Seal the PKI's private keys at rest: the fields become SealedTextField and existing plain keys are sealed."""

from __future__ import annotations

from django.db import migrations

import network.models

TABLES = ("network_authority", "network_clientcertificate")


def seal_existing(apps, schema_editor):
    # Rows load as they are (plain PEM passes through) and are written back sealed.
    for name in ("Authority", "ClientCertificate"):
        model = apps.get_model("network", name)
        for row in model.objects.only("pk", "key_pem").iterator():
            row.save(update_fields=["key_pem"])


def unseal_existing(apps, schema_editor):
    # Back to plain text, written with SQL because the field would seal it again.
    for name, table in zip(("Authority", "ClientCertificate"), TABLES, strict=True):
        model = apps.get_model("network", name)
        with schema_editor.connection.cursor() as cursor:
            for pk, key_pem in model.objects.values_list("pk", "key_pem").iterator():
                cursor.execute(f"UPDATE {table} SET key_pem = %s WHERE id = %s", [key_pem, pk])


class Migration(migrations.Migration):
    dependencies = [("network", "0001_initial")]

    operations = [
        migrations.AlterField(model_name="authority", name="key_pem", field=network.models.SealedTextField()),
        migrations.AlterField(model_name="clientcertificate", name="key_pem", field=network.models.SealedTextField()),
        migrations.RunPython(seal_existing, unseal_existing),
    ]
