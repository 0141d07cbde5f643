"""Routes of the registry's API."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("registry/token", views.TokenView.as_view(), name="registry-token"),
    path("registry/events", views.RegistryEventsView.as_view(), name="registry-events"),
    path("registry/repositories", views.RepositoriesView.as_view(), name="registry-repositories"),
]
