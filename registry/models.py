"""What the cloud knows of its registry's contents: each tag's digest, told by the registry's push notifications."""

from __future__ import annotations

from django.db import models


class RegistryTag(models.Model):
    """A tag of a repository in the cloud's registry and the manifest it points at now."""

    repository = models.CharField(max_length=255, help_text="namespace/name, e.g. alice/detector")
    namespace = models.CharField(max_length=255, db_index=True, help_text="The repository's first path segment.")
    tag = models.CharField(max_length=128)
    digest = models.CharField(max_length=80, help_text="sha256:… of the manifest the tag points at.")
    media_type = models.CharField(max_length=120, blank=True)
    size = models.BigIntegerField(default=0, help_text="The manifest's size in bytes.")
    pushed_by = models.CharField(max_length=150, blank=True)
    pushed_at = models.DateTimeField()

    class Meta:
        ordering = ["repository", "tag"]
        constraints = [models.UniqueConstraint(fields=["repository", "tag"], name="registry_tag_unique")]

    def __str__(self) -> str:
        return f"{self.repository}:{self.tag}@{self.digest}"
