"""REST API v1 of sharing, one module per resource: each view one small APIView with nested
or adjacent Input/Output serializers, calling one service or selector, and answering.

- fields.py: what the views share: serializer fields (base64 envelopes, strict text,
  null-if-blank), the record selection's input (robots, topics, a capture-time window), the
  pagination, the robot-only permission, the schema's security and refusal wording, and the
  caller's credential as the access log records it.
- records.py: uploads from robots, the record list, one record's metadata and its deletion.
- content.py: a record's content, integrity-checked and re-sealed for the caller.
- series.py: numeric fields of a robot's topic over time, every record checked.
- proofs.py: a record's anchoring proof, to check it without the portal.
- grants.py: grants given and received, granting, changing a grant's terms, revoking.
- access.py: the access log.
- exports.py: exports of a selection (create, count, follow, rebuild, download).
- robots.py: a robot's status (last contact, messages per topic).

Refusals are `sharing.errors` (and DRF's), mapped to HTTP in `core.api_errors`. Who may call
what is `accounts.authentication.OwnerCredential`: a robot token uploads and reads its own
uploads' status; everything else needs the owner (a session, or an owner API token with the
`read`, `share` or `delete` scope). Routes are portal/api_urls.py.

Import from the module that serves the resource; this package re-exports nothing.
"""
