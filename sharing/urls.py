"""Owner pages of the sharing app: records, grants, audit."""

from django.urls import path

from sharing import views

urlpatterns = [
    path("records/", views.my_records, name="records"),
    path("shared/", views.shared_records, name="shared"),
    path("records/<uuid:record_id>/", views.record_detail, name="record-detail"),
    path("records/<uuid:record_id>/raw.json", views.record_raw, name="record-raw"),
    path(
        "records/<uuid:record_id>/trajectory.svg",
        views.record_trajectory,
        name="record-trajectory",
    ),
    path("grants/", views.grants, name="grants"),
    path("grants/revoke/", views.grant_revoke_view, name="grant-revoke"),
    path("audit/", views.audit, name="audit"),
    path(
        "account/tokens/<int:token_id>/revoke/",
        views.api_token_revoke,
        name="api-token-revoke",
    ),
]
