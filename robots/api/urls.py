"""Routes of the Robot API about robots."""

from __future__ import annotations

from django.urls import path

from bridgeos_agent.protocol import Event

from . import views

urlpatterns = [
    path("auth", views.AuthView.as_view(), name="auth"),
    path("auth/renew", views.AuthRenewView.as_view(), name="auth-renew"),
    path("robot", views.RobotListView.as_view(), name="robot-list"),
    path("robot/start", views.FleetCommandView.as_view(event=Event.ROBOT_START), name="fleet-start"),
    path("robot/stop", views.FleetCommandView.as_view(event=Event.ROBOT_STOP), name="fleet-stop"),
    path("robot/shutdown", views.FleetCommandView.as_view(event=Event.SHUTDOWN), name="fleet-shutdown"),
    path("robot/<slug:robot_id>", views.RobotDetailView.as_view(), name="robot-detail"),
    path("robot/<slug:robot_id>/info", views.RobotInfoView.as_view(), name="robot-info"),
    path("robot/<slug:robot_id>/token", views.RobotTokenView.as_view(), name="robot-token"),
    path("robot/<slug:robot_id>/bridge-ticket", views.BridgeTicketView.as_view(), name="robot-bridge-ticket"),
    path("robot/<slug:robot_id>/start", views.RobotCommandView.as_view(event=Event.ROBOT_START), name="robot-start"),
    path("robot/<slug:robot_id>/stop", views.RobotCommandView.as_view(event=Event.ROBOT_STOP), name="robot-stop"),
    path("robot/<slug:robot_id>/shutdown", views.RobotCommandView.as_view(event=Event.SHUTDOWN), name="robot-shutdown"),
]
