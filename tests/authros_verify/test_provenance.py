"""An export ties each message to its robot's signature (docs/export.md, "Signatures"): a
tamperer who recomputes every SM3 in the bundle and the MCAP file is still caught, because the
signed plaintext makes the message and only the robot's private key signs another one.
Against the session's anvil, on exports made by the portal's own services."""

import base64
import copy
import json
import struct

import cv2
import numpy as np
import pytest

from accounts.selectors import owner_eoa_account
from authros_verify import (
    BUNDLE_FORMAT,
    BUNDLE_FORMAT_V1,
    BUNDLE_FORMAT_V2,
    ChainReader,
    bundle_digest,
    bundle_serialise,
    verify,
)
from authros_verify.__main__ import main
from authros_verify.mcapfile import mcap_messages
from authros_verify.messages import message_encode, message_log_time
from authros_verify.values import micros
from smcrypto import envelope, provenance, sm2
from tests.authros_verify.conftest import export_of, forged_proof, recomputed
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db

STAMP = {"secs": 1777636800, "nsecs": 123456789}  # 2026-05-01T12:00:00.123456789Z


def _fig4(setup, data_type: str, topic: str, data: object) -> bytes:
    record = {"K": data, "Owner": setup.owner.username, "Type": data_type, "Topic": topic}
    return json.dumps(record, separators=(",", ":")).encode()


def _png() -> str:
    pixels = np.arange(4 * 3 * 3, dtype=np.uint8).reshape(3, 4, 3) * 7
    ok, png = cv2.imencode(".png", pixels)
    assert ok
    return base64.b64encode(png.tobytes()).decode()


def _samples(setup) -> list[tuple[str, str, bytes]]:
    """(type, topic, plaintext) of a record of each kind of message an export makes: CDR
    field by field (odometry, image), CDR from the type's definition, JSON, not JSON."""
    header = {"seq": 0, "stamp": STAMP, "frame_id": "odom"}
    odometry = {
        "header": header,
        "child_frame_id": "base_link",
        "position": {"x": 1.25, "y": -2.5, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.38268343, "w": 0.92387953},
        "linear_velocity": {"x": 0.5, "y": 0.0, "z": 0.0},
        "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.1},
        "pose_covariance": [float(i) for i in range(36)],
        "twist_covariance": [None] + [0.0] * 35,
    }
    image = {
        "header": {**header, "frame_id": "camera"},
        "width": 4,
        "height": 3,
        "encoding": "bgr8",
        "format": "png",
        "data": _png(),
    }
    kinds = [
        ("nav_msgs/Odometry", "/odom", odometry),
        ("sensor_msgs/Image", "/camera", image),
        ("std_msgs/String", "/chatter", {"data": "hello from the robot"}),
        ("acme_msgs/Gripper", "/gripper", {"force": 12.5, "closed": True}),
    ]
    samples = [(kind, topic, _fig4(setup, kind, topic, data)) for kind, topic, data in kinds]
    return [*samples, ("acme_msgs/Blob", "/blob", b"\x00\x01 not JSON \xff")]


def _signed_export(setup, capture) -> tuple[bytes, bytes]:
    envelopes = [
        setup.seal(
            seq,
            topic=topic,
            data_type=data_type,
            time=f"2026-05-01T12:00:0{seq}.123456Z",
            plaintext=plaintext,
        )
        for seq, (data_type, topic, plaintext) in enumerate(_samples(setup))
    ]
    return export_of(setup, capture, envelopes)


@pytest.fixture
def signed_export(make_paired_robot, django_capture_on_commit_callbacks, chain_reader, deployed):
    setup = make_paired_robot("alice")
    bundle, mcap = _signed_export(setup, django_capture_on_commit_callbacks)
    return setup, bundle, mcap, chain_reader, deployed.address


def _failed(report) -> list[tuple[int, str]]:
    return [(result.index, "; ".join(result.problems)) for result in report.failed]


def _next_hex_digit(digit: str) -> str:
    return "0123456789abcdef"[("0123456789abcdef".index(digit) + 1) % 16]


def test_a_signed_export_is_genuine_and_each_byte_of_signer_sig_key_and_plaintext_is_caught(
    signed_export,
):
    setup, bundle, mcap, chain, contract = signed_export
    good = verify(bundle, chain=chain, mcap=mcap, contract=contract)
    assert good.ok, (good.problems, _failed(good))
    assert len(good.genuine) == len(good.records) == 5
    document = json.loads(bundle)
    encodings = [entry["mcap"]["message_encoding"] for entry in document["records"]]
    assert encodings == ["cdr", "cdr", "cdr", "json", "json"]
    for entry, (_type, _topic, plaintext) in zip(document["records"], _samples(setup), strict=True):
        assert base64.b64decode(entry["plaintext"]) == plaintext  # exactly what was sealed
        assert entry["signature"]["public_key"] == sm2.public_key_normalize(setup.signing_key[1])
        assert entry["signature"]["signer"] == setup.robot.key_hash

    # Each hex digit of the signer, the signature and the public key, changed in turn to
    # another hex digit, with the bundle's digest recomputed: caught, and its record named.
    for index in (0, 2):
        for name, expected in (
            ("signer", ("its signer is not the one its anchored envelope names",)),
            ("sig", ("its sig is not the one its anchored envelope carries",)),
            # its 04 marker, then x||y: not a point, or another key than the signer's
            ("public_key", ("its public key is not 04", "its robot signature does not hold")),
        ):
            value = document["records"][index]["signature"][name]
            for position in range(len(value)):
                changed = copy.deepcopy(document)
                digit = _next_hex_digit(value[position])
                changed["records"][index]["signature"][name] = (
                    value[:position] + digit + value[position + 1 :]
                )
                forged, same_mcap = recomputed(changed, mcap)
                report = verify(forged, chain=chain, mcap=same_mcap, contract=contract)
                failed = _failed(report)
                assert [i for i, _ in failed] == [index], (name, position, failed)
                assert any(text in failed[0][1] for text in expected), (name, position, failed)

    # Each byte of a plaintext changed in turn, the MCAP message it makes written in its place
    # and every SM3 recomputed: only the signature tells, and it does.
    for index in range(len(document["records"])):
        entry = document["records"][index]
        plaintext = base64.b64decode(entry["plaintext"])
        for position in range(len(plaintext)):
            changed = copy.deepcopy(document)
            forged_plaintext = bytearray(plaintext)
            forged_plaintext[position] ^= 0x01
            target = changed["records"][index]
            target["plaintext"] = base64.b64encode(forged_plaintext).decode()
            message = message_encode(data_type=entry["type"], plaintext=bytes(forged_plaintext))
            messages = {}
            if (message.message_encoding, message.schema_name) == (
                entry["mcap"]["message_encoding"],
                entry["mcap"]["schema"],
            ):
                messages[entry["mcap"]["sequence"]] = message.data
                log_time = message_log_time(message, micros(entry["captured_at"]) * 1000)
                target["mcap"]["log_time"] = target["mcap"]["publish_time"] = log_time
            forged, forged_mcap = recomputed(changed, mcap, messages=messages)
            report = verify(forged, chain=chain, mcap=forged_mcap, contract=contract)
            failed = _failed(report)
            assert [i for i, _ in failed] == [index], (position, failed)
            assert "its robot signature does not hold (bad_signature" in failed[0][1]


def test_a_changed_mcap_value_is_caught_with_every_sm3_recomputed(signed_export):
    """The attack of issue 34: one value of one odometry message changed with the `mcap`
    library, that message's SM3, the file's SM3 and size and bundle_sm3 recomputed."""
    _setup, bundle, mcap, chain, contract = signed_export
    document = json.loads(bundle)
    odometry = document["records"][0]
    sequence = odometry["mcap"]["sequence"]
    original = next(m for m in mcap_messages(mcap) if m.sequence == sequence).data
    x = struct.pack("<d", 1.25)
    assert original.count(x) == 1
    changed = original.replace(x, struct.pack("<d", 1.5))
    forged, forged_mcap = recomputed(copy.deepcopy(document), mcap, messages={sequence: changed})
    assert forged_mcap != mcap
    report = verify(forged, chain=chain, mcap=forged_mcap, contract=contract)
    assert _failed(report) == [
        (0, "its MCAP message is not the one the plaintext its robot signed makes")
    ]
    assert report.problems == []  # every SM3 of the bundle and the file holds

    # The same on a JSON channel (the Fig. 4 record as sealed), and on the message of a
    # plaintext that is not JSON.
    for index, old, new in ((3, b"12.5", b"13.5"), (4, b"AAE", b"AAI")):
        entry = document["records"][index]
        sequence = entry["mcap"]["sequence"]
        original = next(m for m in mcap_messages(mcap) if m.sequence == sequence).data
        assert old in original
        messages = {sequence: original.replace(old, new)}
        forged, forged_mcap = recomputed(copy.deepcopy(document), mcap, messages=messages)
        report = verify(forged, chain=chain, mcap=forged_mcap, contract=contract)
        assert [i for i, _ in _failed(report)] == [index]

    # A schema that makes readers decode the same bytes as other values (float32 x, say).
    schema = next(m for m in mcap_messages(mcap) if m.sequence == odometry["mcap"]["sequence"])
    reinterpreted = schema.schema_data.replace(b"float64 x", b"float32 x", 1)
    assert reinterpreted != schema.schema_data
    forged, forged_mcap = recomputed(
        copy.deepcopy(document), mcap, schemas={schema.schema: reinterpreted}
    )
    report = verify(forged, chain=chain, mcap=forged_mcap, contract=contract)
    assert _failed(report) == [
        (0, "its message's schema in the MCAP file is not its type's definition")
    ]


def test_a_record_forged_with_the_owners_key_and_eoa_but_not_the_robots_key_fails(
    signed_export, deployed
):
    """Whoever holds the portal's KEK has the owner's SM4 key and EOA, not the robot's SM2
    key: a record sealed, signed by another key and anchored from the owner's EOA fails."""
    setup, bundle, mcap, _chain, contract = signed_export
    document = json.loads(bundle)
    entry = document["records"][2]  # std_msgs/String
    plaintext = _fig4(setup, "std_msgs/String", "/chatter", {"data": "forged"})
    other = sm2.generate_keypair()

    def forge(data: bytes, public_key: str) -> tuple[bytes, bytes]:
        proof = forged_proof(setup, deployed, data)
        header = envelope.read_header(data).header
        changed = copy.deepcopy(document)
        target = changed["records"][2]
        target.update(proof)
        target.update(
            envelope=base64.b64encode(data).decode(),
            plaintext=base64.b64encode(plaintext).decode(),
            seq=header["seq"],
            signature={
                "signer": header["signer"],
                "sig": header["sig"],
                "public_key": sm2.public_key_normalize(public_key),
            },
        )
        message = message_encode(data_type="std_msgs/String", plaintext=plaintext)
        return recomputed(changed, mcap, messages={entry["mcap"]["sequence"]: message.data})

    def sealed(signing_key: tuple[str, str], **header: object) -> bytes:
        return seal_for(
            setup.robot,
            setup.key,
            seq=99,
            topic="/chatter",
            data_type="std_msgs/String",
            time=entry["captured_at"],
            plaintext=plaintext,
            signing_key=signing_key,
        )

    # Signed by a key the chain has never seen.
    data = sealed(other)
    forged, forged_mcap = forge(data, other[1])
    report = verify(forged, chain=ChainReader(deployed.w3), mcap=forged_mcap, contract=contract)
    (failure,) = _failed(report)
    assert failure[0] == 2
    assert "was never registered on chain" in failure[1]

    # Naming the robot's key, signed by another: the signature does not hold under it.
    header = provenance.sign_header(*other, envelope.read_header(data).header, plaintext)
    header["signer"] = setup.robot.key_hash
    data = envelope.seal(setup.key, header, plaintext)
    forged, forged_mcap = forge(data, setup.signing_key[1])
    report = verify(forged, chain=ChainReader(deployed.w3), mcap=forged_mcap, contract=contract)
    (failure,) = _failed(report)
    assert "its robot signature does not hold (bad_signature" in failure[1]

    # The other key registered from the owner's EOA, but after the record was anchored: it was
    # not the owner's key when the record was anchored.
    data = sealed(other)
    forged, forged_mcap = forge(data, other[1])
    other_hash = bytes.fromhex(provenance.key_hash(other[1]))
    deployed.robot_key_add(owner_eoa_account(setup.owner), other_hash, bytes.fromhex(other[1])[1:])
    report = verify(forged, chain=ChainReader(deployed.w3), mcap=forged_mcap, contract=contract)
    (failure,) = _failed(report)
    assert "its robot key was not live when it was anchored" in failure[1]


def test_unsigned_records_are_exported_and_reported_unsigned_never_genuine(
    make_robot,
    django_capture_on_commit_callbacks,
    chain_reader,
    deployed,
    tmp_path,
    capsys,
    isolated_portal,
):
    setup = make_robot("bob")  # a robot added by hand: no key, nothing signed
    envelopes = [
        setup.seal(
            seq, topic="/chatter", data_type="std_msgs/String", time=f"2026-05-01T12:00:0{seq}Z"
        )
        for seq in (1, 2)
    ]
    bundle, mcap = export_of(setup, django_capture_on_commit_callbacks, envelopes)
    document = json.loads(bundle)
    assert document["format"] == BUNDLE_FORMAT == "authros-export-proofs/v3"
    assert [(e["signature"], e["plaintext"]) for e in document["records"]] == [(None, None)] * 2
    report = verify(bundle, chain=chain_reader, mcap=mcap, contract=deployed.address)
    assert report.ok
    assert report.genuine == []
    assert [result.signed for result in report.records] == [False, False]

    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)
    arguments = [
        str(tmp_path / "proofs.json"),
        *("--mcap", str(tmp_path / "export.mcap")),
        *("--rpc", isolated_portal, "--contract", deployed.address),
    ]
    assert main(arguments) == 0
    out = capsys.readouterr().out
    assert out.count("UNSIGNED record") == 2
    assert "2 of 2 records verified against the chain: 0 genuine" in out
    assert "VERIFIED: 2 records, 0 refused, 2 unsigned (not genuine), chain " in out
    assert main([*arguments, "--require-signed"]) == 1

    # An unsigned record that claims a signature, and a signed one passed off as unsigned.
    claimed = copy.deepcopy(document)
    claimed["records"][0]["signature"] = {"signer": "0" * 64, "sig": "0" * 128, "public_key": "04"}
    report = verify(recomputed(claimed, mcap)[0], chain=chain_reader, contract=deployed.address)
    assert _failed(report) == [
        (0, "its envelope is unsigned, yet it states a signature or a plaintext")
    ]

    # Unsigned records in a bundle of either older format still verify, never genuine.
    for label, dropped in ((BUNDLE_FORMAT_V2, ()), (BUNDLE_FORMAT_V1, ("signature", "plaintext"))):
        old = _relabelled(document, label, dropped)
        report = verify(old, chain=chain_reader, mcap=mcap, contract=deployed.address)
        assert report.ok, (label, report.problems, _failed(report))
        assert [result.signed for result in report.records] == [False, False]


def _relabelled(document: dict, label: str, dropped: tuple[str, ...]) -> bytes:
    """The bundle as an older exporter wrote it: `label`, without the v3 fields (topic_seq,
    batch, streams) and the `dropped` fields of each record, its digest recomputed."""
    old = copy.deepcopy(document)
    old["format"] = label
    del old["streams"]
    for entry in old["records"]:
        for name in ("topic_seq", "batch", *dropped):
            del entry[name]
    old["bundle_sm3"] = bundle_digest(old)
    return bundle_serialise(old)


def test_a_signed_record_cannot_pass_as_unsigned_in_any_format(signed_export):
    _setup, bundle, mcap, chain, contract = signed_export
    document = json.loads(bundle)
    stripped = copy.deepcopy(document)
    stripped["records"][1].update(signature=None, plaintext=None)
    report = verify(recomputed(stripped, mcap)[0], chain=chain, mcap=mcap, contract=contract)
    assert _failed(report) == [
        (1, "its envelope is signed by a robot, but its signature or plaintext is null")
    ]

    # Relabelled to the first format (which carries no signatures): whether a record is signed
    # is its anchored envelope's, so each of these signed records fails, none passes unsigned.
    v1 = _relabelled(document, BUNDLE_FORMAT_V1, ("signature", "plaintext"))
    report = verify(v1, chain=chain, mcap=mcap, contract=contract)
    assert [index for index, _ in _failed(report)] == [0, 1, 2, 3, 4]
    assert all("its anchored envelope is signed by robot key" in why for _, why in _failed(report))
    assert report.not_genuine == []

    # The second format (signatures, no topic_seq) still reads its signed records: genuine.
    v2 = _relabelled(document, BUNDLE_FORMAT_V2, ())
    report = verify(v2, chain=chain, mcap=mcap, contract=contract)
    assert report.ok, (report.problems, _failed(report))
    assert len(report.genuine) == 5
