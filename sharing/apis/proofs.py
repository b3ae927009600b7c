"""`/api/v1/records/{id}/proof/`: a record's anchoring proof (the audit path, the anchor,
the stored envelope and the robot's signature; for a v2 record its batch and topic_seq), to
check it without the portal."""

import base64
import contextlib

from drf_spectacular.utils import extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from chainworker.services import chain_client
from core.api_errors import error_responses
from sharing.apis.fields import (
    OWNER_ONLY,
    READ,
    RECORD_ID,
    ROBOT_REFUSED,
    record_uuid,
    refuse_unseen,
)
from sharing.cache import envelope_fetch
from sharing.errors import NotAnchoredYet
from sharing.models import Record
from sharing.selectors.records import record_list_visible_to, record_proof
from sharing.verification.signature import record_batch, record_signature


class ProofAnchorSerializer(serializers.Serializer):
    class Meta:
        ref_name = "ProofAnchor"

    chain_id = serializers.IntegerField()
    contract = serializers.CharField(help_text="the AuthROS contract's address")
    sender = serializers.CharField(help_text="the account that anchored it (the owner's)")
    tx = serializers.CharField()
    block = serializers.IntegerField(allow_null=True)


class ProofSignatureSerializer(serializers.Serializer):
    class Meta:
        ref_name = "ProofSignature"

    signer = serializers.CharField(help_text="SM3 of the robot's public key x||y, hex")
    public_key = serializers.CharField(help_text="the robot's SM2 public key, 04||x||y hex")
    sig = serializers.CharField(help_text="the SM2 signature r||s, hex (DESIGN.md Provenance)")
    key_owner = serializers.CharField(
        allow_null=True,
        help_text="the record's owner EOA when robotKeyOfOwner(owner, signer) says it registered "
        "the key; null when it never did (whoever else did)",
    )
    key_added_block = serializers.IntegerField(allow_null=True)
    key_revoked_block = serializers.IntegerField(allow_null=True, help_text="null: live")


class ProofBatchSerializer(serializers.Serializer):
    class Meta:
        ref_name = "ProofBatch"

    sig_index = serializers.IntegerField(help_text="the record's leaf index in its batch")
    sig_size = serializers.IntegerField(help_text="the number of records the batch signed")
    sig_path = serializers.CharField(
        help_text="the leaf's audit path in the batch's tree: 64 lowercase hex per hash, "
        "concatenated, leaf side first (RFC 9162 2.1.3), as the envelope's header carries it"
    )
    root = serializers.CharField(
        allow_null=True,
        help_text="the batch root the record's leaf folds to, lowercase hex: what `sig` is "
        "over (DESIGN.md Provenance v2); null if it does not fold",
    )


class RecordProofApi(APIView):
    """`GET /api/v1/records/{id}/proof/`: the record's anchoring proof."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read a record's proof")]

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordProof"

        record = serializers.UUIDField()
        owner = serializers.CharField(help_text="the owner's EOA")
        digest = serializers.CharField(help_text="SM3 of the envelope, 0x hex")
        mode = serializers.ChoiceField(choices=["root", "record"])
        leaf_index = serializers.IntegerField()
        tree_size = serializers.IntegerField()
        path = serializers.ListField(
            child=serializers.CharField(), help_text="the audit path, leaf up (RFC 9162 2.1.3)"
        )
        root = serializers.CharField(help_text="the anchored root (record mode: the digest)")
        anchor = ProofAnchorSerializer()
        envelope = serializers.CharField(
            allow_null=True,
            help_text="the anchored envelope as stored, base64; null once the record is deleted",
        )
        signature = ProofSignatureSerializer(
            allow_null=True, help_text="the robot's signature; null for an unsigned record"
        )
        batch = ProofBatchSerializer(
            required=False,
            help_text="a v2 record's place in the batch its robot signed once (absent for v1 "
            "and unsigned records, and once the record is deleted)",
        )
        topic_seq = serializers.IntegerField(
            required=False,
            help_text="a v2 record's number in its signer's count of its topic (absent for v1 "
            "and unsigned records, and once the record is deleted)",
        )

    @extend_schema(
        operation_id="records_proof",
        summary="The record's anchoring proof, to check it without the portal",
        description=(
            "Root mode: SM3 the envelope, make the leaf SM3(0x00 || owner || record id || "
            "digest), fold the path (RFC 9162 2.1.3.2) to the root, and call "
            "rootOf(sender, root) on the contract: its size must be tree_size. Record mode: "
            "dataQueryOf(owner, record id) holds the digest. `envelope` is the stored envelope and "
            "`signature` the robot's: SM3 of public_key must be signer, the SM2 signature over "
            "the record's plaintext must hold (DESIGN.md Provenance), and "
            "robotKeyOfOwner(owner, signer) must say the owner added the key at or before the "
            "anchoring block and had not revoked it by then (robotKeyOf names only the first "
            "owner that added it). A v2 record (DESIGN.md Provenance v2) adds `batch` and "
            "`topic_seq`: its leaf folded up `batch.sig_path` at `batch.sig_index` in a tree "
            'of `batch.sig_size` gives `batch.root`, and `sig` holds over "AuthROS/batch-'
            'signature/v2" || 0x00 || sig_size (8 bytes, big-endian) || root. For the owner or '
            "a grantee (a session, or an owner API token with the `read` scope)."
        ),
        auth=OWNER_ONLY,
        parameters=[RECORD_ID],
        responses={
            200: OutputSerializer,
            **error_responses(
                401,
                403,
                404,
                409,
                e403=ROBOT_REFUSED.format(scope="read"),
                e404="`not_found`: no such record, or not shared with you",
                e409="`not_anchored_yet`: the record is not on chain yet",
            ),
        },
    )
    def get(self, request: Request, record_id: str) -> Response:
        record = (
            record_list_visible_to(caller_owner(request))
            .select_related("owner", "anchor_root")
            .filter(pk=record_uuid(record_id))
            .first()
        )
        if record is None:
            refuse_unseen(request, record_uuid(record_id))
        if record.status != Record.Status.ANCHORED:
            raise NotAnchoredYet("the record is not anchored yet; try again shortly")
        client = chain_client()
        proof = record_proof(record, chain_id=client.chain_id, contract=client.address)
        proof["envelope"] = proof["signature"] = None
        # A deleted record's envelope is gone (its proof stays); one removed behind the
        # portal's back too: the check at the next view says so.
        with contextlib.suppress(FileNotFoundError):
            if not record.is_deleted:
                data, _source = envelope_fetch(record)
                proof["envelope"] = base64.b64encode(data).decode("ascii")
                proof["signature"] = record_signature(record, data, client)
                batch = record_batch(record, data)
                if batch is not None:
                    proof["topic_seq"] = batch.pop("topic_seq")
                    proof["batch"] = batch
        return Response(self.OutputSerializer(proof).data)
