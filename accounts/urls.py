"""Owner pages of the accounts app: registration, sign-in, key, robots, API tokens."""

from django.contrib.auth import views as auth_views
from django.urls import path

from accounts import views

urlpatterns = [
    path("register/", views.register, name="register"),
    path("register/progress/", views.registration_progress, name="registration-progress"),
    path("login/", views.LoginView.as_view(), name="login"),
    path("logout/", auth_views.LogoutView.as_view(), name="logout"),
    path("account/status.json", views.account_status, name="account-status"),
    path("account/password/", views.PasswordChangeView.as_view(), name="password_change"),
    path("account/key/", views.key_rotation, name="key-rotation"),
    path("robots/", views.robots, name="robots"),
    path("robots/pair/", views.robot_pair, name="robot-pair"),
    path("robots/<uuid:robot_id>/revoke/", views.robot_revoke, name="robot-revoke"),
    path("robots/<uuid:robot_id>/retention/", views.robot_retention, name="robot-retention"),
    path("robots/<uuid:robot_id>/agent.yaml", views.robot_config, name="robot-config"),
    # Revoking one is sharing's page (`api-token-revoke`): it takes back the grants it made.
    path("account/tokens/", views.api_tokens, name="api-tokens"),
]
