"""Empty the tables between tests with DELETE under the locks a TRUNCATE takes, not with TRUNCATE.

pytest-django empties every table after each transactional test with one TRUNCATE. On PostgreSQL
a TRUNCATE gives each table new files and syncs them at commit: about a seventh of a second for
this schema's sixty-odd tables, a test, almost all of them already empty. Deleting the rows costs
next to nothing for an empty table. The tables are first locked as the TRUNCATE locks them, in the
same order, so a write still in flight is waited for and emptied too (and a deadlock with one is
retried, see flushretry). The foreign keys Django makes are deferred to the commit, when every
table is empty; the replica role keeps the audit log's append-only triggers out of the way, as
they are out of a TRUNCATE's.
"""

from __future__ import annotations

from typing import Any


def delete_instead_of_truncate() -> None:
    """Make PostgreSQL's flush delete every table's rows under exclusive locks instead of truncating."""
    from django.db.backends.postgresql.operations import DatabaseOperations

    truncate = DatabaseOperations.sql_flush
    if getattr(truncate, "deletes", False):
        return

    def sql_flush(
        self: Any, style: Any, tables: list[str], *, reset_sequences: bool = False, allow_cascade: bool = False
    ) -> list[str]:
        if reset_sequences or allow_cascade or not tables:
            return truncate(self, style, tables, reset_sequences=reset_sequences, allow_cascade=allow_cascade)
        names = [self.quote_name(table) for table in tables]
        return [
            f"LOCK TABLE {', '.join(names)} IN ACCESS EXCLUSIVE MODE",
            "SET LOCAL session_replication_role = replica",
            *(f"DELETE FROM {name}" for name in names),
        ]

    sql_flush.deletes = True  # type: ignore[attr-defined]
    DatabaseOperations.sql_flush = sql_flush  # type: ignore[method-assign]
