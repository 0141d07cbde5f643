"""Routes of the Robot API about organizations, members and scoped tokens."""

from __future__ import annotations

from django.urls import path

from . import views

urlpatterns = [
    path("organizations", views.OrganizationListView.as_view(), name="organization-list"),
    path("organizations/<str:slug>", views.OrganizationDetailView.as_view(), name="organization-detail"),
    path("organizations/<str:slug>/members", views.MemberListView.as_view(), name="organization-members"),
    path(
        "organizations/<str:slug>/members/<str:username>",
        views.MemberDetailView.as_view(),
        name="organization-member",
    ),
    path("organizations/<str:slug>/tokens", views.OrganizationTokenListView.as_view(), name="organization-tokens"),
    path("tokens", views.TokenListView.as_view(), name="token-list"),
    path("tokens/<int:token_id>", views.TokenDetailView.as_view(), name="token-detail"),
]
