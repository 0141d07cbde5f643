"""Routes of the Robot API about recordings."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("robot/<slug:robot_id>/recordings", views.RecordingListView.as_view(), name="recording-list"),
    path(
        "robot/<slug:robot_id>/recordings/<slug:recording_id>",
        views.RecordingDetailView.as_view(),
        name="recording-detail",
    ),
    path(
        "robot/<slug:robot_id>/recordings/<slug:recording_id>/stop",
        views.RecordingStopView.as_view(),
        name="recording-stop",
    ),
    path(
        "robot/<slug:robot_id>/recordings/<slug:recording_id>/download",
        views.RecordingDownloadView.as_view(),
        name="recording-download",
    ),
]
