"""Anchoring record digests: single and batch uploads, ids write-once per owner and bound to it
(issue 38: nobody squats another owner's id), dataQuery/dataCheck and their ...Of forms."""

from eth_utils import keccak

ZERO32 = b"\0" * 32
ZERO_ADDRESS = "0x0000000000000000000000000000000000000000"
BLOCK_GAS_LIMIT = 30_000_000


def batch_args(records):
    """Column-wise arguments of dataUploadBatch from (id, digest, time, dataType) rows."""
    ids, digests, times, types = (list(column) for column in zip(*records, strict=True))
    return ids, digests, times, types


def mine(call, sender):
    """A view of the caller's own records (dataQuery/dataCheck read msg.sender's), as `sender`."""
    return call.call({"from": sender})


def test_upload_anchors_a_record(authros, alice, record, send, emitted):
    record_id, digest, time, data_type = record(0)

    receipt = send(authros.functions.dataUpload(record_id, digest, time, data_type), alice)

    assert emitted(receipt, "DataUploaded") == [
        {"id": record_id, "owner": alice, "digest": digest, "time": time, "dataType": data_type}
    ]
    assert mine(authros.functions.dataQuery(record_id), alice) == [
        alice,
        digest,
        time,
        data_type,
    ]
    assert authros.functions.recordCount().call() == 1


def test_upload_accepts_zero_time_and_type(authros, alice, record, send):
    record_id, digest, _, _ = record(0)
    send(authros.functions.dataUpload(record_id, digest, 0, ZERO32), alice)
    assert mine(authros.functions.dataQuery(record_id), alice) == [
        alice,
        digest,
        0,
        ZERO32,
    ]


def test_upload_keeps_full_uint64_time(authros, alice, record, send):
    record_id, digest, _, data_type = record(0)
    latest = 2**64 - 1
    send(authros.functions.dataUpload(record_id, digest, latest, data_type), alice)
    assert mine(authros.functions.dataQuery(record_id), alice) == [
        alice,
        digest,
        latest,
        data_type,
    ]


def test_upload_refuses_unregistered(authros, enrolled_only, outsider, record, reverts):
    for caller in (enrolled_only, outsider):
        with reverts("NotRegistered", caller):
            authros.functions.dataUpload(*record(0)).transact({"from": caller})


def test_upload_refuses_empty_id(authros, alice, record, reverts):
    _, digest, time, data_type = record(0)
    with reverts("EmptyId"):
        authros.functions.dataUpload(ZERO32, digest, time, data_type).transact({"from": alice})


def test_upload_refuses_empty_digest(authros, alice, record, reverts):
    record_id, _, time, data_type = record(0)
    with reverts("EmptyDigest"):
        authros.functions.dataUpload(record_id, ZERO32, time, data_type).transact({"from": alice})


def test_upload_is_write_once_per_owner(authros, alice, record, send, reverts):
    record_id, digest, time, data_type = record(0)
    send(authros.functions.dataUpload(record_id, digest, time, data_type), alice)
    with reverts("RecordExists", record_id):
        authros.functions.dataUpload(record_id, keccak(text="forged"), time, data_type).transact(
            {"from": alice}
        )
    assert mine(authros.functions.dataQuery(record_id), alice) == [
        alice,
        digest,
        time,
        data_type,
    ]


def test_another_owner_cannot_squat_a_record_id(authros, alice, bob, record, send):
    """Bob anchors first under the id Alice's record will have: Alice's upload still succeeds
    and her record reads back as hers; Bob's is his own, under his address only."""
    record_id, digest, time, data_type = record(0)
    squat = keccak(text="squatted")
    send(authros.functions.dataUpload(record_id, squat, time, data_type), bob)
    send(authros.functions.dataUpload(record_id, digest, time, data_type), alice)
    assert authros.functions.dataQueryOf(alice, record_id).call() == [
        alice,
        digest,
        time,
        data_type,
    ]
    assert authros.functions.dataQueryOf(bob, record_id).call() == [bob, squat, time, data_type]
    assert authros.functions.dataCheckOf(alice, record_id, digest).call() is True
    assert authros.functions.dataCheckOf(alice, record_id, squat).call() is False
    assert mine(authros.functions.dataCheck(record_id, squat), bob) is True


def test_batch_anchors_every_record_in_order(authros, alice, record, send, emitted):
    records = [record(n) for n in range(5)]

    receipt = send(authros.functions.dataUploadBatch(*batch_args(records)), alice)

    assert emitted(receipt, "DataUploaded") == [
        {"id": i, "owner": alice, "digest": d, "time": t, "dataType": k} for i, d, t, k in records
    ]
    for record_id, digest, time, data_type in records:
        assert mine(authros.functions.dataQuery(record_id), alice) == [
            alice,
            digest,
            time,
            data_type,
        ]
    assert authros.functions.recordCount().call() == 5


def test_batch_refuses_unregistered(authros, outsider, record, reverts):
    with reverts("NotRegistered", outsider):
        authros.functions.dataUploadBatch(*batch_args([record(0)])).transact({"from": outsider})


def test_batch_is_not_refused_for_an_id_another_owner_took(authros, alice, bob, record, send):
    send(authros.functions.dataUpload(*record(2)), bob)
    records = [record(n) for n in range(4)]
    assert send(authros.functions.dataUploadBatch(*batch_args(records)), alice)["status"] == 1
    assert authros.functions.recordCount().call() == 5


def test_batch_names_the_first_taken_id(authros, alice, record, send, reverts):
    send(authros.functions.dataUpload(*record(3)), alice)
    send(authros.functions.dataUpload(*record(1)), alice)
    records = [record(n) for n in range(5)]

    with reverts("RecordExists", record(1)[0]):
        authros.functions.dataUploadBatch(*batch_args(records)).transact({"from": alice})


def test_batch_refuses_a_duplicate_inside_itself(authros, alice, record, reverts):
    records = [record(0), record(1), record(0)]
    with reverts("RecordExists", record(0)[0]):
        authros.functions.dataUploadBatch(*batch_args(records)).transact({"from": alice})


def test_batch_retry_without_the_taken_id_succeeds(authros, alice, record, send, reverts):
    send(authros.functions.dataUpload(*record(1)), alice)
    records = [record(n) for n in range(3)]
    with reverts("RecordExists", record(1)[0]):
        authros.functions.dataUploadBatch(*batch_args(records)).transact({"from": alice})

    retry = [r for r in records if r[0] != record(1)[0]]
    send(authros.functions.dataUploadBatch(*batch_args(retry)), alice)

    assert authros.functions.recordCount().call() == 3


def test_batch_is_all_or_nothing_when_mined(w3, authros, alice, record, send):
    """Sent with explicit gas (no estimate to stop it), the failing batch is mined and undone."""
    send(authros.functions.dataUpload(*record(2)), alice)
    records = [record(n) for n in range(4)]

    tx_hash = authros.functions.dataUploadBatch(*batch_args(records)).transact(
        {"from": alice, "gas": 1_000_000}
    )
    receipt = w3.eth.wait_for_transaction_receipt(tx_hash)

    assert receipt["status"] == 0
    assert receipt["logs"] == []
    assert mine(authros.functions.dataQuery(record(0)[0]), alice) == [
        ZERO_ADDRESS,
        ZERO32,
        0,
        ZERO32,
    ]
    assert authros.functions.recordCount().call() == 1


def test_batch_refuses_empty_id_and_digest(authros, alice, record, reverts):
    good, (record_id, digest, time, data_type) = record(0), record(1)
    with reverts("EmptyId"):
        authros.functions.dataUploadBatch(
            *batch_args([good, (ZERO32, digest, time, data_type)])
        ).transact({"from": alice})
    with reverts("EmptyDigest"):
        authros.functions.dataUploadBatch(
            *batch_args([good, (record_id, ZERO32, time, data_type)])
        ).transact({"from": alice})


def test_batch_refuses_length_mismatch(authros, alice, record, reverts):
    ids, digests, times, types = batch_args([record(0), record(1)])
    mismatched = [
        (ids[:1], digests, times, types),
        (ids, digests[:1], times, types),
        (ids, digests, times[:1], types),
        (ids, digests, times, types[:1]),
    ]
    for args in mismatched:
        with reverts("BatchLengthMismatch"):
            authros.functions.dataUploadBatch(*args).transact({"from": alice})


def test_batch_refuses_empty_batch(authros, alice, reverts):
    with reverts("EmptyBatch"):
        authros.functions.dataUploadBatch([], [], [], []).transact({"from": alice})


def test_batch_refuses_more_than_max_batch(authros, alice, record, reverts):
    records = [record(n) for n in range(257)]
    with reverts("BatchTooLarge", 257, 256):
        authros.functions.dataUploadBatch(*batch_args(records)).transact({"from": alice})


def test_max_batch_fits_in_a_30m_gas_block(authros, alice, record, send, emitted):
    max_batch = authros.functions.MAX_BATCH().call()
    records = [record(n) for n in range(max_batch)]

    # Explicit gas: the batch at the block gas limit, not an estimate with its margin.
    receipt = send(authros.functions.dataUploadBatch(*batch_args(records)), alice, BLOCK_GAS_LIMIT)

    assert receipt["gasUsed"] < BLOCK_GAS_LIMIT
    assert len(emitted(receipt, "DataUploaded")) == max_batch
    assert authros.functions.recordCount().call() == max_batch
    last_id, last_digest, _, _ = records[-1]
    assert mine(authros.functions.dataCheck(last_id, last_digest), alice) is True


def test_query_of_unknown_id_is_all_zeros(authros, alice, record):
    assert mine(authros.functions.dataQuery(record(0)[0]), alice) == [
        ZERO_ADDRESS,
        ZERO32,
        0,
        ZERO32,
    ]
    assert mine(authros.functions.dataQuery(ZERO32), alice) == [
        ZERO_ADDRESS,
        ZERO32,
        0,
        ZERO32,
    ]


def test_check_matches_only_the_anchored_digest(authros, alice, record, send):
    record_id, digest, time, data_type = record(0)
    unknown_id, _, _, _ = record(1)
    send(authros.functions.dataUpload(record_id, digest, time, data_type), alice)

    assert mine(authros.functions.dataCheck(record_id, digest), alice) is True
    assert mine(authros.functions.dataCheck(record_id, keccak(text="tampered")), alice) is False
    assert mine(authros.functions.dataCheck(record_id, ZERO32), alice) is False
    assert mine(authros.functions.dataCheck(unknown_id, digest), alice) is False
    assert mine(authros.functions.dataCheck(unknown_id, ZERO32), alice) is False


def test_records_survive_key_rotation(authros, alice, record, send):
    record_id, digest, time, data_type = record(0)
    send(authros.functions.dataUpload(record_id, digest, time, data_type), alice)

    send(authros.functions.rotateKey(keccak(text="new key")), alice)

    assert mine(authros.functions.dataQuery(record_id), alice) == [
        alice,
        digest,
        time,
        data_type,
    ]
    assert mine(authros.functions.dataCheck(record_id, digest), alice) is True
