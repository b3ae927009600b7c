"""What the verifier's tests share: signed text messages to export, an export made through
the portal's own services, and the export as a tamperer leaves it, with every SM3 and size
recomputed (the `mcap` library, not the portal's writer, rewrites the MCAP file)."""

import io
import json
import uuid
from collections.abc import Callable, Sequence

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from accounts.selectors import owner_eoa_account
from authros_verify import ChainReader, bundle_digest, bundle_serialise
from chainworker.client import AuthROSChain
from sharing.exports.create import export_create
from sharing.exports.download import export_download
from sharing.models import Export
from sharing.services.uploads import record_create_batch
from smcrypto import envelope
from smcrypto.merkle import leaf_hash
from smcrypto.sm3 import sm3_hex
from tests.support.robot_setup import RobotSetup


def chatter_envelopes(setup: RobotSetup, seqs: Sequence[int]) -> list[bytes]:
    """The robot's std_msgs/String messages "msg SEQ" on /chatter, sealed (and signed when
    the robot is paired), one per upload sequence number."""
    return [
        setup.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            plaintext=json.dumps({"K": {"data": f"msg {seq}"}}).encode(),
        )
        for seq in seqs
    ]


def export_of(
    setup: RobotSetup, capture: Callable, envelopes: Sequence[bytes]
) -> tuple[bytes, bytes]:
    """Upload the envelopes as the robot (anchored inline), export everything its owner may
    view: (bundle, mcap)."""
    with capture(execute=True):
        record_create_batch(robot=setup.robot, envelopes=list(envelopes))
    with capture(execute=True):
        export = export_create(requester=setup.owner)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    mcap, bundle = export_files(export)
    return bundle, mcap


def export_files(export: Export) -> tuple[bytes, bytes]:
    """(MCAP file, proof bundle) of a ready export, as its requester downloads them (stored
    sealed, decrypted as streamed)."""
    return tuple(
        b"".join(
            export_download(requester=export.requester, export_id=export.pk, part=part).chunks()
        )
        for part in ("mcap", "bundle")
    )


def mcap_rewritten(
    mcap: bytes,
    *,
    messages: dict[int, bytes] | None = None,
    schemas: dict[str, bytes] | None = None,
    compression: CompressionType = CompressionType.NONE,
    chunk_size: int | None = None,
) -> bytes:
    """The MCAP file written again with the `mcap` library: the messages of the given
    sequences and the schemas of the given names replaced, everything else kept; its chunks
    compressed with `compression`, of `chunk_size` bytes (the library's default if None)."""
    messages, schemas = messages or {}, schemas or {}
    reader = make_reader(io.BytesIO(mcap))
    header = reader.get_header()
    output = io.BytesIO()
    sized = {} if chunk_size is None else {"chunk_size": chunk_size}
    writer = Writer(output, compression=compression, **sized)
    writer.start(profile=header.profile, library=header.library)
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        if schema.id not in schema_ids:
            data = schemas.get(schema.name, schema.data)
            schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, data)
        if channel.id not in channel_ids:
            channel_ids[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding, schema_ids[schema.id]
            )
        writer.add_message(
            channel_ids[channel.id],
            log_time=message.log_time,
            data=messages.get(message.sequence, message.data),
            publish_time=message.publish_time,
            sequence=message.sequence,
        )
    writer.finish()
    return output.getvalue()


def recomputed(
    document: dict,
    mcap: bytes,
    *,
    messages: dict[int, bytes] | None = None,
    schemas: dict[str, bytes] | None = None,
) -> tuple[bytes, bytes]:
    """The export as a tamperer leaves it: the MCAP file rewritten with the changed messages
    and schemas, each changed message's SM3, the file's SM3 and size and `bundle_sm3`
    recomputed, the bundle in its canonical form."""
    messages = messages or {}
    if messages or schemas:
        mcap = mcap_rewritten(mcap, messages=messages, schemas=schemas)
    for entry in document["records"]:
        if entry["mcap"]["sequence"] in messages:
            entry["mcap"]["sm3"] = "0x" + sm3_hex(messages[entry["mcap"]["sequence"]])
    document["mcap"] = {**document["mcap"], "size": len(mcap), "sm3": "0x" + sm3_hex(mcap)}
    document["bundle_sm3"] = bundle_digest(document)
    return bundle_serialise(document), mcap


@pytest.fixture
def chain_reader(deployed) -> ChainReader:
    """One reader for a whole test: the chain's answers asked once each (a test that changes
    the chain makes a reader of its own)."""
    return ChainReader(deployed.w3)


def forged_proof(setup: RobotSetup, client: AuthROSChain, data: bytes) -> dict:
    """What whoever holds the portal's KEK can do without any robot: anchor an envelope they
    sealed with the owner's key from the owner's own EOA (a tree of one leaf). Its proof, as
    `GET /api/v1/records/{id}/proof/` answers one."""
    account = owner_eoa_account(setup.owner)
    record = uuid.uuid4()
    root = leaf_hash(account.address, record, envelope.digest(data))
    anchored = client.anchor_root(account, root, 1, client.last_root_of(account.address))
    return {
        "record": str(record),
        "owner": account.address,
        "digest": "0x" + envelope.digest(data).hex(),
        "mode": "root",
        "leaf_index": 0,
        "tree_size": 1,
        "path": [],
        "root": "0x" + root.hex(),
        "anchor": {
            "chain_id": client.chain_id,
            "contract": client.address,
            "sender": account.address,
            "tx": anchored.tx_hash,
            "block": anchored.block_number,
        },
    }
