"""Routes of the owner pages of the sharing app (sharing/views/, one module per page group)."""

from django.urls import path

from sharing.views import (
    access_log,
    audit,
    deletion,
    exports,
    grants,
    record,
    records,
    robot,
    tokens,
)

urlpatterns = [
    path("records/", records.my_records, name="records"),
    path("shared/", records.shared_records, name="shared"),
    path("records/<uuid:record_id>/", record.record_detail, name="record-detail"),
    path("records/<uuid:record_id>/raw.json", record.record_raw, name="record-raw"),
    path("records/<uuid:record_id>/gallery/", record.record_gallery, name="record-gallery"),
    path("records/<uuid:record_id>/delete/", deletion.record_delete_view, name="record-delete"),
    path("records/delete/", deletion.records_delete_view, name="records-delete"),
    path("account/delete/", deletion.account_delete_view, name="account-delete"),
    path("robots/<uuid:robot_id>/", robot.robot_page, name="robot-detail"),
    path("grants/", grants.grants, name="grants"),
    path("grants/revoke/", grants.grant_revoke_view, name="grant-revoke"),
    path("grants/revoke/confirm/", grants.grant_revoke_confirm, name="grant-revoke-confirm"),
    path("audit/", audit.audit, name="audit"),
    path("access-log/", access_log.access_log, name="access-log"),
    path("access-log/access-log.csv", access_log.access_log_download, name="access-log-csv"),
    path("exports/", exports.exports, name="exports"),
    path("exports/<uuid:export_id>/", exports.export_detail, name="export-detail"),
    path("exports/<uuid:export_id>/rebuild/", exports.export_rebuild_view, name="export-rebuild"),
    path(
        "account/tokens/<int:token_id>/revoke/",
        tokens.api_token_revoke,
        name="api-token-revoke",
    ),
]
