"""The audit chain: append-only in PostgreSQL, verified by `manage.py audit verify`, a tampered row found."""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.core.management import call_command
from django.core.management.base import CommandError
from django.db import DatabaseError, connection, transaction

from audit import services
from audit.models import GENESIS, AuditAnchor, AuditEntry

pytestmark = pytest.mark.django_db(transaction=True)


def write(count: int) -> list[AuditEntry]:
    """Write entries as a door would."""
    return [
        services.record("robot.update", door="rest", actor="alice", target=f"robot/bot-{index}", data={"n": index})
        for index in range(count)
    ]


def tamper(sql: str, params: list) -> None:
    """Change the table behind the trigger's back, as someone with the database's owner rights could."""
    with connection.cursor() as cursor:
        cursor.execute("ALTER TABLE audit_auditentry DISABLE TRIGGER USER")
        try:
            cursor.execute(sql, params)
        finally:
            cursor.execute("ALTER TABLE audit_auditentry ENABLE TRIGGER USER")


def test_each_entry_chains_to_the_one_before(capsys):
    entries = write(4)
    assert entries[0].prev_hash == GENESIS
    assert [entry.prev_hash for entry in entries[1:]] == [entry.hash for entry in entries[:-1]]
    call_command("audit", "verify")
    assert capsys.readouterr().out.strip() == "audit chain intact: 4 entries verified"


def test_rows_cannot_be_changed_or_deleted_through_the_database():
    entry = write(1)[0]
    for attempt in (
        lambda: AuditEntry.objects.filter(pk=entry.pk).update(actor="mallory"),
        lambda: AuditEntry.objects.filter(pk=entry.pk).delete(),
    ):
        with pytest.raises(DatabaseError, match="append-only"), transaction.atomic():
            attempt()
    assert AuditEntry.objects.get(pk=entry.pk).actor == "alice"


def test_an_edited_row_is_found_by_verify(capsys):
    entries = write(5)
    tamper("UPDATE audit_auditentry SET actor = 'mallory' WHERE id = %s", [entries[2].pk])
    with pytest.raises(CommandError, match=f"broken at entry {entries[2].pk}: hash mismatch"):
        call_command("audit", "verify")
    assert "2 entries verified before the break" in capsys.readouterr().out


def test_an_edited_row_with_its_hash_recomputed_breaks_the_next_link():
    entries = write(4)
    forged = AuditEntry.objects.get(pk=entries[1].pk)
    forged.outcome = "denied"
    tamper("UPDATE audit_auditentry SET outcome = 'denied', hash = %s WHERE id = %s", [forged.digest(), forged.pk])
    with pytest.raises(CommandError, match=f"broken at entry {entries[2].pk}: prev_hash mismatch"):
        call_command("audit", "verify")


def test_a_deleted_row_is_found_by_verify():
    entries = write(4)
    tamper("DELETE FROM audit_auditentry WHERE id = %s", [entries[1].pk])
    with pytest.raises(CommandError, match=f"broken at entry {entries[2].pk}: prev_hash mismatch"):
        call_command("audit", "verify")
    tamper("DELETE FROM audit_auditentry WHERE id = %s", [entries[0].pk])
    with pytest.raises(CommandError, match=f"broken at entry {entries[2].pk}: .*no anchor"):
        call_command("audit", "verify")


def test_retention_removes_old_entries_and_anchors_the_chain(capsys):
    write(3)
    assert services.prune_entries(timedelta(seconds=0)) == 3
    anchor = AuditAnchor.objects.get()
    kept = AuditEntry.objects.get()
    assert (kept.action, kept.door, kept.id, kept.prev_hash) == (
        "audit.retention",
        "system",
        anchor.first_id,
        anchor.prev_hash,
    )
    write(2)
    call_command("audit", "verify")
    assert "3 entries verified" in capsys.readouterr().out
    assert services.prune_entries(timedelta(days=1)) == 0  # nothing that old now


def test_the_verify_walk_spans_batches(capsys):
    write(25)
    call_command("audit", "verify", "--batch", "7")
    assert "25 entries verified" in capsys.readouterr().out
    with pytest.raises(CommandError, match="--batch"):
        call_command("audit", "verify", "--batch", "0")
