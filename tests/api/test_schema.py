"""The OpenAPI schema: valid, served, and describing exactly the API that DESIGN.md fixes."""

from io import StringIO
from pathlib import Path

import pytest
import yaml
from django.core.management import call_command

from accounts.keyexchange import portal_sm2_public_key, sm4_key_from_submission
from smcrypto import sm2, sm4

pytestmark = pytest.mark.django_db

# DESIGN.md, "REST API for agents (fixed)"
FIXED_OPERATIONS = {
    ("/api/v1/sm2-public-key/", "get"),
    ("/api/v1/records/", "get"),
    ("/api/v1/records/", "post"),
    ("/api/v1/records/{record_id}/", "get"),
    ("/api/v1/records/{record_id}/content/", "get"),
    ("/api/v1/records/{record_id}/proof/", "get"),
    ("/api/v1/grants/", "get"),
    ("/api/v1/grants/", "post"),
    ("/api/v1/grants/{grantee}/", "delete"),
}
# Added by issue 14 (robot pairing), beside the fixed ones.
PAIRING_OPERATIONS = {
    ("/api/v1/robot-pairings/", "post"),
    ("/api/v1/robot-pairings/{pairing_id}/collect/", "post"),
    ("/api/v1/robot-key/", "get"),
}
# Added by issue 16 (the owner's access log).
ACCESS_LOG_OPERATIONS = {("/api/v1/access-log/", "get")}
# Added by issue 16 (export with proofs, docs/export.md).
EXPORT_OPERATIONS = {
    ("/api/v1/exports/", "get"),
    ("/api/v1/exports/", "post"),
    ("/api/v1/exports/{export_id}/", "get"),
    ("/api/v1/exports/{export_id}/{part}/", "get"),
    # Issue 35: the count before exporting; issue 37: rebuilding a withdrawn export.
    ("/api/v1/exports/count/", "get"),
    ("/api/v1/exports/{export_id}/rebuild/", "post"),
}
# Added by issue 16 (scoped grants): changing a grant's terms.
GRANT_TERMS_OPERATIONS = {("/api/v1/grants/{grantee}/", "patch")}
# Added by issue 16 (deletion): the owner deletes a record.
DELETION_OPERATIONS = {("/api/v1/records/{record_id}/", "delete")}
# Added by issue 35: numeric fields of a robot's topic over time, every record checked.
SERIES_OPERATIONS = {("/api/v1/records/series/", "get")}
# Added by issue 35 (the robot page): a robot's last contact and rates.
ROBOT_STATUS_OPERATIONS = {("/api/v1/robots/{robot_id}/status/", "get")}
# Added by issue 44: every record counted, each stream's gaps with their reasons.
COMPLETENESS_OPERATIONS = {("/api/v1/records/completeness/", "get")}


def test_the_schema_validates_without_warnings(tmp_path: Path):
    out = tmp_path / "schema.yaml"
    call_command(
        "spectacular", "--validate", "--fail-on-warn", "--file", str(out), stderr=StringIO()
    )
    assert yaml.safe_load(out.read_text())["openapi"].startswith("3.")


def test_the_served_schema_lists_exactly_the_fixed_endpoints(client):
    answer = client.get("/api/schema/", HTTP_ACCEPT="application/vnd.oai.openapi+json")
    assert answer.status_code == 200
    schema = answer.json()
    operations = {
        (path, method)
        for path, item in schema["paths"].items()
        for method in item
        if method in {"get", "post", "put", "patch", "delete"}
    }
    assert operations == (
        FIXED_OPERATIONS
        | PAIRING_OPERATIONS
        | ACCESS_LOG_OPERATIONS
        | EXPORT_OPERATIONS
        | GRANT_TERMS_OPERATIONS
        | DELETION_OPERATIONS
        | SERIES_OPERATIONS
        | ROBOT_STATUS_OPERATIONS
        | COMPLETENESS_OPERATIONS
    )
    assert schema["paths"]["/api/v1/robot-key/"]["get"]["security"] == [{"robotToken": []}]
    for path in ("/api/v1/robot-pairings/", "/api/v1/robot-pairings/{pairing_id}/collect/"):
        # No credentials yet: the request secret travels in the body, never in the URL.
        assert schema["paths"][path]["post"].get("security", [{}]) == [{}], path
    error = {"$ref": "#/components/schemas/Error"}
    for path, method in operations:
        responses = schema["paths"][path][method]["responses"]
        errors = {code for code in responses if code.startswith(("4", "5"))}
        assert "429" in errors, (path, method)
        for code in errors:
            assert responses[code]["content"]["application/json"]["schema"] == error
    upload = schema["paths"]["/api/v1/records/"]["post"]
    assert upload["security"] == [{"robotToken": []}]
    assert {"400", "401", "403", "409", "413"} <= set(upload["responses"])
    schemes = schema["components"]["securitySchemes"]
    assert schemes["robotToken"]["name"] == schemes["ownerToken"]["name"] == "Authorization"
    # Content and grants are the owner's: a session or an owner API token, never a robot's.
    owner_only = [{"ownerToken": []}, {"cookieAuth": []}]
    for path, method in [
        ("/api/v1/records/{record_id}/content/", "get"),
        ("/api/v1/records/{record_id}/proof/", "get"),
        ("/api/v1/grants/", "get"),
        ("/api/v1/grants/", "post"),
        ("/api/v1/grants/{grantee}/", "delete"),
        ("/api/v1/access-log/", "get"),
        ("/api/v1/records/{record_id}/", "delete"),
        ("/api/v1/records/series/", "get"),
        ("/api/v1/records/completeness/", "get"),
    ]:
        assert schema["paths"][path][method]["security"] == owner_only, (path, method)
    for path in ("/api/v1/records/", "/api/v1/records/{record_id}/"):
        security = schema["paths"][path]["get"]["security"]
        assert {"robotToken": []} in security, path
        assert {"ownerToken": []} in security, path
    assert set(schema["components"]["schemas"]["Error"]["required"]) == {"error", "detail"}


def test_swagger_ui_is_served(client):
    answer = client.get("/api/docs/")
    assert answer.status_code == 200
    assert b"swagger" in answer.content.lower()


def test_the_sm2_public_key_needs_no_credentials_and_works_for_the_key_exchange(client):
    answer = client.get("/api/v1/sm2-public-key/")
    assert answer.status_code == 200
    body = answer.json()
    assert body == {"public_key": portal_sm2_public_key(), "mode": "C1C3C2"}
    key = sm4.generate_key()
    assert sm4_key_from_submission(sm2.encrypt(body["public_key"], key)) == key


def test_anything_else_under_api_is_a_json_404(client):
    for path in ("/api/", "/api/v1/", "/api/v2/records/", "/api/v1/records", "/api/v1/robots/"):
        for method in ("get", "post", "delete"):
            answer = getattr(client, method)(path)
            assert answer.status_code == 404, (method, path)
            assert answer.json()["error"] == "not_found"
    assert "slash" in client.post("/api/v1/records").json()["detail"]


def test_methods_the_api_does_not_have_get_405(client, make_owner, make_owner_token):
    _, key = make_owner_token(make_owner())
    auth = {"HTTP_AUTHORIZATION": f"Token {key}"}
    for method, path in [
        ("put", "/api/v1/records/"),
        ("delete", "/api/v1/records/"),
        ("post", "/api/v1/sm2-public-key/"),
        ("patch", "/api/v1/grants/"),
        ("get", "/api/v1/grants/bob/"),
    ]:
        answer = getattr(client, method)(path, **auth)
        assert answer.status_code == 405, (method, path)
        assert answer.json()["error"] == "method_not_allowed"


def test_the_upload_documents_its_storage_refusal(client):
    """An upload the storage cannot make durable is answered 503 storage_unavailable: the
    schema says so, so that an agent's author retries it."""
    schema = client.get("/api/schema/", HTTP_ACCEPT="application/vnd.oai.openapi+json").json()
    responses = schema["paths"]["/api/v1/records/"]["post"]["responses"]
    assert "storage_unavailable" in responses["503"]["description"]
