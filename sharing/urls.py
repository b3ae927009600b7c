"""Owner pages of the sharing app: records, grants, audit."""

from django.urls import path

from sharing import robot_views, views

urlpatterns = [
    path("records/", views.my_records, name="records"),
    path("shared/", views.shared_records, name="shared"),
    path("records/<uuid:record_id>/", views.record_detail, name="record-detail"),
    path("records/<uuid:record_id>/raw.json", views.record_raw, name="record-raw"),
    path("records/<uuid:record_id>/gallery/", views.record_gallery, name="record-gallery"),
    path("records/<uuid:record_id>/delete/", views.record_delete_view, name="record-delete"),
    path("records/delete/", views.records_delete_view, name="records-delete"),
    path("account/delete/", views.account_delete_view, name="account-delete"),
    path("robots/<uuid:robot_id>/", robot_views.robot_page, name="robot-detail"),
    path("grants/", views.grants, name="grants"),
    path("grants/revoke/", views.grant_revoke_view, name="grant-revoke"),
    path("grants/revoke/confirm/", views.grant_revoke_confirm, name="grant-revoke-confirm"),
    path("audit/", views.audit, name="audit"),
    path("access-log/", views.access_log, name="access-log"),
    path("access-log/access-log.csv", views.access_log_download, name="access-log-csv"),
    path("exports/", views.exports, name="exports"),
    path("exports/<uuid:export_id>/", views.export_detail, name="export-detail"),
    path("exports/<uuid:export_id>/rebuild/", views.export_rebuild_view, name="export-rebuild"),
    path(
        "account/tokens/<int:token_id>/revoke/",
        views.api_token_revoke,
        name="api-token-revoke",
    ),
]
