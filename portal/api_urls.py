"""Routes of the REST API (`/api/`): v1 for agents and owners, the schema and its docs."""

from django.urls import include, path, re_path
from drf_spectacular.views import SpectacularAPIView, SpectacularSwaggerSplitView

from accounts.apis import RobotKeyApi, RobotPairingCollectApi, RobotPairingsApi, Sm2PublicKeyApi
from core.api_errors import api_not_found
from sharing.apis.access import AccessLogApi
from sharing.apis.completeness import RecordCompletenessApi
from sharing.apis.content import RecordContentApi
from sharing.apis.exports import (
    ExportCountApi,
    ExportDetailApi,
    ExportFileApi,
    ExportRebuildApi,
    ExportsApi,
)
from sharing.apis.grants import GrantRevokeApi, GrantsApi
from sharing.apis.proofs import RecordProofApi
from sharing.apis.records import RecordDetailApi, RecordsApi
from sharing.apis.robots import RobotStatusApi
from sharing.apis.series import RecordSeriesApi

v1 = [
    path("sm2-public-key/", Sm2PublicKeyApi.as_view(), name="sm2-public-key"),
    path("robot-pairings/", RobotPairingsApi.as_view(), name="robot-pairings"),
    path(
        "robot-pairings/<str:pairing_id>/collect/",
        RobotPairingCollectApi.as_view(),
        name="robot-pairing-collect",
    ),
    path("robot-key/", RobotKeyApi.as_view(), name="robot-key"),
    path("records/", RecordsApi.as_view(), name="records"),
    path("records/series/", RecordSeriesApi.as_view(), name="records-series"),
    path("records/completeness/", RecordCompletenessApi.as_view(), name="records-completeness"),
    path("records/<str:record_id>/", RecordDetailApi.as_view(), name="record-detail"),
    path("records/<str:record_id>/content/", RecordContentApi.as_view(), name="record-content"),
    path("records/<str:record_id>/proof/", RecordProofApi.as_view(), name="record-proof"),
    path("grants/", GrantsApi.as_view(), name="grants"),
    path("exports/", ExportsApi.as_view(), name="exports"),
    path("exports/count/", ExportCountApi.as_view(), name="export-count"),
    path("exports/<str:export_id>/", ExportDetailApi.as_view(), name="export-detail"),
    path("exports/<str:export_id>/rebuild/", ExportRebuildApi.as_view(), name="export-rebuild"),
    path(
        "exports/<str:export_id>/<str:part>/",
        ExportFileApi.as_view(),
        name="export-file",
    ),
    path("grants/<str:grantee>/", GrantRevokeApi.as_view(), name="grant-revoke"),
    path("access-log/", AccessLogApi.as_view(), name="access-log"),
    path("robots/<str:robot_id>/status/", RobotStatusApi.as_view(), name="robot-status"),
]

urlpatterns = [
    path("v1/", include((v1, "api-v1"))),
    path("schema/", SpectacularAPIView.as_view(), name="api-schema"),
    # Its script is a file of its own (`?script`): the Content-Security-Policy runs no inline one.
    path("docs/", SpectacularSwaggerSplitView.as_view(url_name="api-schema"), name="api-docs"),
    # Last: anything else under /api/ answers a JSON 404 (and is not redirected to a slash).
    re_path(r"^.*$", api_not_found),
]
