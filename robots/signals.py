"""Signals other apps follow about robots."""

from __future__ import annotations

from django.dispatch import Signal

# Sent with robot=... inside the transaction that replaced a robot's token.
credentials_rotated = Signal()
