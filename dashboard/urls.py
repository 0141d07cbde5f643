"""Routes of the operator dashboard, mounted at /."""

from __future__ import annotations

from django.urls import path

from . import views

app_name = "dashboard"

urlpatterns = [
    path("", views.fleet, name="index"),
    path("robots/<slug:robot_id>/", views.robot, name="robot"),
    path("skills/", views.skills, name="skills"),
    path("images/", views.images, name="images"),
    path("events/", views.events, name="events"),
    path("validate/skill-config", views.validate_config, {"kind": "skill"}, name="validate-skill-config"),
    path("validate/robot-config", views.validate_config, {"kind": "robot"}, name="validate-robot-config"),
]
