"""Routes of the Robot API about component logs."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("robot/<slug:robot_id>/logs", views.LogListView.as_view(), name="log-list"),
    path("robot/<slug:robot_id>/logs/download", views.LogDownloadView.as_view(), name="log-download"),
]
