"""Routes of the Robot API about monitoring."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("database/query", views.DatabaseQueryView.as_view(), name="database-query"),
    path("events", views.EventListView.as_view(), name="event-list"),
]
