"""Routes of the Robot API about releases and rollouts."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("releases", views.ReleaseListView.as_view(), name="release-list"),
    path("releases/<int:release_id>", views.ReleaseDetailView.as_view(), name="release-detail"),
    path("rollouts", views.RolloutListView.as_view(), name="rollout-list"),
    path("rollouts/<int:rollout_id>", views.RolloutDetailView.as_view(), name="rollout-detail"),
    path(
        "rollouts/<int:rollout_id>/pause",
        views.RolloutActionView.as_view(action_name="pause"),
        name="rollout-pause",
    ),
    path(
        "rollouts/<int:rollout_id>/resume",
        views.RolloutActionView.as_view(action_name="resume"),
        name="rollout-resume",
    ),
    path(
        "rollouts/<int:rollout_id>/abort",
        views.RolloutActionView.as_view(action_name="abort"),
        name="rollout-abort",
    ),
    path("robot/<slug:robot_id>/hold", views.HoldView.as_view(), name="robot-hold"),
]
