"""The owner's alerts page: choices, webhook endpoints, the delivery log."""

from django.urls import path

from alerts import views

urlpatterns = [
    path("account/alerts/", views.alert_settings, name="alerts"),
    path("account/alerts/webhooks/", views.webhook_create, name="alert-webhook-create"),
    path(
        "account/alerts/webhooks/<uuid:endpoint_id>/delete/",
        views.webhook_delete,
        name="alert-webhook-delete",
    ),
    path("account/alerts/test/", views.alert_test, name="alert-test"),
    path("account/alerts/verify/<str:token>/", views.email_verify, name="alert-email-verify"),
]
