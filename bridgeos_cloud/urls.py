"""URL routes: dashboard at /, admin at /admin/, the Robot API under /api/."""

from __future__ import annotations

from django.contrib import admin
from django.contrib.auth import views as auth_views
from django.urls import include, path
from drf_spectacular.views import SpectacularAPIView, SpectacularSwaggerView

from audit import views as audit_views
from monitoring import views as monitoring_views

from . import views

urlpatterns = [
    path("", include("dashboard.urls")),
    path("accounts/login/", views.limited_login(auth_views.LoginView.as_view()), name="login"),
    path("accounts/logout/", auth_views.LogoutView.as_view(), name="logout"),
    path("admin/login/", views.limited_login(admin.site.login)),  # before admin/: same limits as /api/auth
    path("admin/", admin.site.urls),
    path("audit/", audit_views.audit_page, name="audit"),
    path("api/health", views.health, name="health"),
    path("metrics", monitoring_views.metrics, name="metrics"),
    path("api/", include("robots.api.urls")),
    path("api/", include("skills.api.urls")),
    path("api/", include("monitoring.api.urls")),
    path("api/", include("network.api.urls")),
    path("api/", include("recordings.api.urls")),
    path("api/", include("registry.api.urls")),
    path("api/", include("teams.api.urls")),
    path("api/", include("audit.api.urls")),
    path("api/", include("rollouts.api.urls")),
    path("api/", include("logs.api.urls")),
    path("api/schema/", SpectacularAPIView.as_view(), name="schema"),
    path("api/docs/", SpectacularSwaggerView.as_view(url_name="schema"), name="docs"),
]

admin.site.site_header = "bridgeOS Cloud administration"
admin.site.site_title = "bridgeOS Cloud"
