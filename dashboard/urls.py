"""Routes of the operator dashboard, mounted at /."""

from __future__ import annotations

from django.urls import path

from . import teamviews, views

app_name = "dashboard"

urlpatterns = [
    path("", views.fleet, name="index"),
    path("fleet/page", views.fleet_data, name="fleet-page"),
    path("robots/<slug:robot_id>/", views.robot, name="robot"),
    path("robots/<slug:robot_id>/logs/", views.robot_logs, name="robot-logs"),
    path("skills/", views.skills, name="skills"),
    path("images/", views.images, name="images"),
    path("events/", views.events, name="events"),
    path("rollouts/", views.rollouts, name="rollouts"),
    path("rollouts/<int:rollout_id>/", views.rollout, name="rollout"),
    path("organization", teamviews.pick_organization, name="pick-organization"),
    path("organizations/", teamviews.organizations, name="organizations"),
    path("organizations/<str:slug>/", teamviews.organization, name="organization"),
    path("organizations/<str:slug>/members/<str:username>", teamviews.member, name="member"),
    path("tokens/", teamviews.api_tokens, name="tokens"),
    path("tokens/<int:token_id>/revoke", teamviews.revoke_api_token, name="revoke-token"),
    path("validate/skill-config", views.validate_config, {"kind": "skill"}, name="validate-skill-config"),
    path("validate/robot-config", views.validate_config, {"kind": "robot"}, name="validate-robot-config"),
]
