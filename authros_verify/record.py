"""`authros_verify record`: one record, as the portal serves it to its owner or a grantee,
checked without trusting the portal.

The portal's two answers (`GET /api/v1/records/{id}/content/`: the content re-sealed under the
caller's own key; `GET /api/v1/records/{id}/proof/`: the anchored envelope, its proof and the
robot's signature) are checked against each other, the caller's own SM4 key and a chain node
the caller chose. Each check is named, in this order:

- `chain`: the node is the proof's chain, and the contract is the one the caller expects;
- `anchored envelope`: the proof's envelope is this record's and hashes (SM3) to its digest;
- `merkle path` and `rootOf` (root mode), or `merkle path` and `dataQuery` (record mode): the
  digest is anchored on chain by the record's owner, in the block the proof names;
- `decryption`: the content opens under the caller's key (SM4-GCM);
- `same record`: the content is the anchored record's (same id, digest and header, the
  plaintext as long as the anchored ciphertext; the very plaintext when the caller's key opens
  the anchored envelope too, as the owner's does);
- `signature`: the anchored envelope's header names the signer and signature the proof gives,
  the public key hashes to the signer, and the signature holds over that header and the
  plaintext the caller decrypted; for a record signed in a batch (provenance v2, read from
  that header), its leaf folds up its path to the root the batch's signature is over, and the
  proof's `batch` and `topic_seq`, when it gives them, are the header's and that root;
- `robotKeyOf`: the chain names the record's owner as the key's, live at the anchoring block.

A check that needs one that failed is not made (and says so). The record is genuine when
all hold; an unsigned record (a robot added by hand) never is.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from authros_verify.anchor import Anchored, anchor_check
from authros_verify.chain import ChainReader
from authros_verify.signature import is_signed, robot_key_check, signature_check
from authros_verify.values import Invalid, address, base64_bytes, hash32, whole
from smcrypto import envelope, provenance
from smcrypto.envelope import BATCH_FIELDS, EnvelopeInfo, provenance_format
from smcrypto.errors import CryptoError, SignatureInvalid, WrongKey

CHECKS = (
    "chain",
    "anchored envelope",
    "merkle path",
    "rootOf",
    "dataQuery",
    "decryption",
    "same record",
    "signature",
    "robotKeyOf",
)


@dataclass(frozen=True)
class Outcome:
    check: str
    holds: bool | None  # None: not made (it needs a check that failed), or unsigned
    detail: str


@dataclass
class RecordCheck:
    record: str
    outcomes: list[Outcome] = field(default_factory=list)
    signed: bool | None = None  # None: not known (a check before it failed)
    plaintext: bytes | None = None  # the content, once every check holds

    @property
    def failed(self) -> list[Outcome]:
        return [outcome for outcome in self.outcomes if outcome.holds is False]

    @property
    def genuine(self) -> bool:
        return not self.failed and self.signed is True

    def holds(self, check: str, detail: str) -> None:
        self.outcomes.append(Outcome(check, True, detail))

    def fails(self, check: str, detail: str) -> None:
        self.outcomes.append(Outcome(check, False, detail))

    def not_made(self, check: str, detail: str) -> None:
        self.outcomes.append(Outcome(check, None, detail))


@dataclass(frozen=True)
class _Chain:
    chain_id: int
    contract: str


def record_check(
    *,
    record: str,
    content: Any,
    proof: Any,
    key: bytes,
    chain: ChainReader,
    contract: str | None = None,
    chain_id: int | None = None,
    allow_unsigned: bool = False,
) -> RecordCheck:
    """Check the portal's content and proof answers for `record` with the caller's SM4 key
    against the chain. `contract` and `chain_id` are what the caller knows independently;
    without them the proof's own are used. Raises ChainUnreachable if the node cannot be
    asked. The plaintext is kept only when every check holds (and the record is signed, or
    `allow_unsigned`)."""
    result = RecordCheck(record)
    # An answer that is not an object fails every check that reads it.
    content = content if isinstance(content, Mapping) else {}
    proof = proof if isinstance(proof, Mapping) else {}
    on = _check_chain(result, proof, chain, contract, chain_id)
    sealed = _check_anchored_envelope(result, record, proof)
    anchored = _check_anchoring(result, proof, chain, on)
    opened = _check_decryption(result, content, key)
    same = _check_same_record(result, record, content, proof, key, sealed, opened)
    signer = _check_signature(result, proof, sealed, opened, same, allow_unsigned)
    _check_robot_key(result, chain, on, anchored, signer)
    if not result.failed and opened is not None and (result.signed or allow_unsigned):
        result.plaintext = opened[1]
    return result


def _check_chain(
    result: RecordCheck,
    proof: Mapping[str, Any],
    chain: ChainReader,
    contract: str | None,
    chain_id: int | None,
) -> _Chain | None:
    try:
        anchor = proof["anchor"]
        stated_id = whole(anchor["chain_id"], "anchor.chain_id")
        stated_contract = address(anchor["contract"], "anchor.contract")
    except (Invalid, KeyError, TypeError) as exc:
        result.fails("chain", f"the proof names no chain and contract ({exc})")
        return None
    actual_id = chain.chain_id()
    if stated_id != actual_id or (chain_id is not None and chain_id != actual_id):
        expected = stated_id if chain_id is None else chain_id
        result.fails("chain", f"the node is chain {actual_id}, not chain {expected}")
        return None
    if contract is not None and stated_contract.lower() != contract.lower():
        result.fails(
            "chain", f"the proof names contract {stated_contract}, not the expected {contract}"
        )
        return None
    if not chain.has_code(stated_contract):
        result.fails("chain", f"there is no contract at {stated_contract} on chain {actual_id}")
        return None
    pinned = "the contract expected" if contract is not None else "as the proof names it"
    result.holds("chain", f"chain {actual_id}, contract {stated_contract} ({pinned})")
    return _Chain(actual_id, stated_contract)


def _check_anchored_envelope(
    result: RecordCheck, record: str, proof: Mapping[str, Any]
) -> EnvelopeInfo | None:
    check = "anchored envelope"
    try:
        if proof.get("record") != record:
            raise Invalid(f"the proof is of record {proof.get('record')!r}, not {record}")
        if proof.get("envelope") is None:
            raise Invalid("the proof gives no envelope (a deleted record's is gone)")
        data = base64_bytes(proof["envelope"], "envelope")
        if envelope.digest(data) != hash32(proof.get("digest"), "digest"):
            raise Invalid("the proof's envelope does not hash (SM3) to its digest")
        sealed = envelope.read_header(data)
    except Invalid as exc:
        result.fails(check, str(exc))
        return None
    except CryptoError as exc:
        result.fails(check, f"the proof's envelope does not parse: {exc}")
        return None
    result.holds(check, f"its SM3 is the proof's digest {proof['digest']}")
    return sealed


def _check_anchoring(
    result: RecordCheck, proof: Mapping[str, Any], chain: ChainReader, on: _Chain | None
) -> Anchored | None:
    mode = proof.get("mode")
    slot = "dataQuery" if mode == "record" else "rootOf"
    if on is None:
        for check in ("merkle path", slot):
            result.not_made(check, "needs the chain check")
        return None
    try:
        anchored = anchor_check(
            dict(proof), chain=chain, chain_id=on.chain_id, contract=on.contract
        )
    except Invalid as exc:
        failed = exc.check if exc.check in ("merkle path", slot) else "merkle path"
        if failed == slot:
            result.holds("merkle path", "the proof's path holds")
        result.fails(failed, str(exc))
        if failed == "merkle path":
            result.not_made(slot, "needs the merkle path check")
        return None
    if mode == "root":
        result.holds(
            "merkle path",
            f"leaf {proof['leaf_index']} of {proof['tree_size']} folds to root {proof['root']}",
        )
        result.holds(slot, f"the root is anchored by {anchored.owner} in block {anchored.block}")
    else:
        result.holds("merkle path", "record mode: the digest is anchored by itself")
        result.holds(slot, f"the digest is anchored by {anchored.owner} in block {anchored.block}")
    return anchored


def _check_decryption(
    result: RecordCheck, content: Mapping[str, Any], key: bytes
) -> tuple[dict[str, Any], bytes] | None:
    try:
        data = base64_bytes(content.get("envelope"), "content envelope")
        opened = envelope.open(key, data)
    except Invalid as exc:
        result.fails("decryption", str(exc))
        return None
    except WrongKey as exc:
        result.fails("decryption", f"the content is not sealed under your key: {exc}")
        return None
    except CryptoError as exc:
        result.fails("decryption", f"the content does not open under your key: {exc}")
        return None
    result.holds("decryption", f"{len(opened[1])} bytes, opened with your key (SM4-GCM)")
    return opened


def _check_same_record(
    result: RecordCheck,
    record: str,
    content: Mapping[str, Any],
    proof: Mapping[str, Any],
    key: bytes,
    sealed: EnvelopeInfo | None,
    opened: tuple[dict[str, Any], bytes] | None,
) -> bool:
    check = "same record"
    if sealed is None or opened is None:
        result.not_made(check, "needs the anchored envelope and the decryption checks")
        return False
    header, plaintext = opened
    anchored_plaintext = None
    try:
        if content.get("id") != record:
            raise Invalid(f"the content is of record {content.get('id')!r}, not {record}")
        if not _same_hex(content.get("digest"), proof.get("digest")):
            raise Invalid("the content answer names another digest than the proof")
        if header != sealed.header:
            changed = sorted(
                name
                for name in set(header) | set(sealed.header)
                if header.get(name) != sealed.header.get(name)
            )
            raise Invalid(f"the content's header differs from the anchored one in {changed}")
        if len(plaintext) != sealed.ciphertext_length:
            raise Invalid("the content is not as long as the anchored ciphertext")
        if sealed.key_id == envelope.key_id(key):
            anchored_plaintext = envelope.open(key, base64_bytes(proof["envelope"], "envelope"))[1]
            if anchored_plaintext != plaintext:
                raise Invalid("the content is not the anchored envelope's plaintext")
    except Invalid as exc:
        result.fails(check, str(exc))
        return False
    except CryptoError as exc:
        result.fails(check, f"the anchored envelope does not open under your key: {exc}")
        return False
    how = (
        "the anchored envelope opens under your key to the very same plaintext"
        if anchored_plaintext is not None
        else "same id, digest and header; the plaintext as long as the anchored ciphertext"
    )
    result.holds(check, how)
    return True


def _same_hex(one: Any, other: Any) -> bool:
    """Whether two hex texts (with or without 0x) are the same bytes: the content answer
    states its digest without 0x, the proof with it."""
    texts = [value.lower().removeprefix("0x") for value in (one, other) if isinstance(value, str)]
    return len(texts) == 2 and texts[0] == texts[1]


def _check_signature(
    result: RecordCheck,
    proof: Mapping[str, Any],
    sealed: EnvelopeInfo | None,
    opened: tuple[dict[str, Any], bytes] | None,
    same: bool,
    allow_unsigned: bool,
) -> str | None:
    """The signer whose signature holds, or None."""
    check = "signature"
    if sealed is None or opened is None or not same:
        result.not_made(check, "needs the anchored envelope, decryption and same record checks")
        return None
    signature = proof.get("signature")
    if not is_signed(sealed.header):
        if signature is not None:
            result.fails(check, "the proof gives a signature, but the anchored envelope has none")
            return None
        result.signed = False
        unsigned = "unsigned: no robot signed this record (a robot added by hand)"
        if allow_unsigned:
            result.not_made(check, unsigned)
        else:
            result.fails(check, unsigned + "; it is not genuine (--allow-unsigned to read it)")
        return None
    try:
        if not isinstance(signature, Mapping):
            raise Invalid("the anchored envelope is signed, but the proof gives no signature")
        public_key = signature.get("public_key")
        signature_check(
            header=sealed.header,
            plaintext=opened[1],
            signer=signature.get("signer"),
            sig=signature.get("sig"),
            public_key=public_key.lower() if isinstance(public_key, str) else public_key,
        )
        batched = _batch_check(proof, sealed.header, opened[1])
    except Invalid as exc:
        result.fails(check, str(exc))
        return None
    result.signed = True
    signer = sealed.header["signer"]
    result.holds(check, f"robot key {signer} signed {batched or 'this header and plaintext'} (SM2)")
    return signer


def _batch_check(proof: Mapping[str, Any], header: Mapping[str, Any], plaintext: bytes) -> str:
    """For a record signed in a batch (v2, as its anchored envelope's header says): the
    proof's `topic_seq` and `batch`, when given, against the header and the root its leaf
    folds to; what was signed, in words. "" for a record signed alone (v1)."""
    if provenance_format(header) != "v2":
        return ""
    try:
        root = "0x" + provenance.batch_root(header, plaintext).hex()
    except SignatureInvalid as exc:  # cannot happen once the signature held
        raise Invalid(f"its batch path does not fold: {exc}", check="signature") from None
    if "topic_seq" in proof and proof["topic_seq"] != header["topic_seq"]:
        raise Invalid("the proof's topic_seq is not the anchored envelope's", check="signature")
    stated = proof.get("batch")
    if stated is not None:
        place = {name: header[name] for name in BATCH_FIELDS}
        if (
            not isinstance(stated, Mapping)
            or set(stated) != {*BATCH_FIELDS, "root"}
            or {name: stated[name] for name in BATCH_FIELDS} != place
            or not _same_hex(stated["root"], root)  # with or without 0x
        ):
            raise Invalid(
                "the proof's batch (sig_index, sig_size, sig_path, root) is not the anchored "
                "envelope's and the root its record folds to",
                check="signature",
            )
    return (
        f"its upload batch of {header['sig_size']} records (root {root}), this record "
        f"#{header['sig_index']}, topic_seq {header['topic_seq']} on {header['topic']}"
    )


def _check_robot_key(
    result: RecordCheck,
    chain: ChainReader,
    on: _Chain | None,
    anchored: Anchored | None,
    signer: str | None,
) -> None:
    check = "robotKeyOf"
    if result.signed is False:
        return  # unsigned: no key to ask about
    if on is None or anchored is None or signer is None:
        result.not_made(check, "needs the chain, anchoring and signature checks")
        return
    try:
        robot_key_check(
            chain, contract=on.contract, signer=signer, owner=anchored.owner, block=anchored.block
        )
    except Invalid as exc:
        result.fails(check, str(exc))
        return
    result.holds(check, f"the key is {anchored.owner}'s on chain, live at block {anchored.block}")
