"""Routes of the Robot API about robots' networks."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("robot/<slug:robot_id>/vpn", views.RobotVpnView.as_view(), name="robot-vpn"),
]
