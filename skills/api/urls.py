"""Routes of the Robot API about skills, components and the catalog."""

from __future__ import annotations

from django.urls import path

from . import componentsapi, views

SKILL = "robot/<slug:robot_id>/skill/<slug:skill_id>"
COMPONENT = f"{SKILL}/component/<slug:component_id>"

urlpatterns = [
    path("cloud/manager/<str:token>/<path:path>", componentsapi.components_api, name="cloud-components-api"),
    path("robot/<slug:robot_id>/volumes", views.RobotVolumesView.as_view(), name="robot-volumes"),
    path("robot/<slug:robot_id>/skill/add", views.SkillAddView.as_view(), name="skill-add"),
    path("robot/<slug:robot_id>/skill/remove", views.SkillRemoveView.as_view(), name="skill-remove"),
    path(f"{SKILL}/info", views.SkillInfoView.as_view(), name="skill-info"),
    path(f"{SKILL}/start", views.SkillStartView.as_view(), name="skill-start"),
    path(f"{SKILL}/stop", views.SkillStopView.as_view(), name="skill-stop"),
    path(f"{COMPONENT}/info", views.ComponentInfoView.as_view(), name="component-info"),
    path(f"{COMPONENT}/start", views.ComponentStartView.as_view(), name="component-start"),
    path(f"{COMPONENT}/stop", views.ComponentStopView.as_view(), name="component-stop"),
    path(f"{COMPONENT}/migrate", views.ComponentMigrateView.as_view(), name="component-migrate"),
    path("templates", views.SkillTemplateListView.as_view(), name="template-list"),
    path("templates/<int:template_id>", views.SkillTemplateDetailView.as_view(), name="template-detail"),
]
