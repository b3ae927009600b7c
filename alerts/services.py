"""Alerts: what the domain apps publish, the owner's choices, and the deliveries.

The apps that see something happen call one of the `*_alert` functions inside the same
transaction as what happened: the alert and its deliveries are written with it, and each
delivery is queued (alerts.tasks.alert_deliver) on commit; the watch re-queues any lost. The
watched conditions (a silent robot, low gas) are checked by the beat task `alerts_watch`, and
alert once per episode: an open AlertCondition holds back the next alert until the state ends.
"""

import hashlib
import json
import logging
import secrets
import time
import uuid
from collections.abc import Sequence
from datetime import datetime, timedelta
from decimal import Decimal

from django.conf import settings
from django.core import signing
from django.core.mail import EmailMessage
from django.db import IntegrityError, transaction
from django.utils import timezone

from accounts.keywrap import unwrap, wrap
from accounts.models import Owner
from alerts.errors import (
    DeliveryFailed,
    EmailLinkInvalid,
    InvalidAlertPreferences,
    TooManyWebhooks,
    WebhookUrlRefused,
)
from alerts.models import (
    Alert,
    AlertCondition,
    AlertDelivery,
    AlertKind,
    AlertPreferences,
    WebhookEndpoint,
)
from alerts.selectors import (
    alert_conditions_open,
    alert_preferences_of,
    deliveries_stale,
    owners_watching_gas,
    robots_silent,
    webhook_endpoints_of,
)
from alerts.webhooks import webhook_post, webhook_signature, webhook_url_check
from chainworker.errors import ChainError
from chainworker.services import chain_client
from core.outbox import enqueue

logger = logging.getLogger(__name__)

WEI_PER_ETHER = Decimal(10) ** 18
WEBHOOK_SECRET_PREFIX = "whsec_"  # noqa: S105 (a prefix that names the secret, not one)
# Limits of the owner's settings: a silent robot after 5 minutes to 30 days.
ROBOT_SILENT_MINUTES_MIN = 5
ROBOT_SILENT_MINUTES_MAX = 30 * 24 * 60
# Record ids listed in one anchoring-failed alert (the count says how many there were).
RECORDS_LISTED = 20
# What owners choose among; the test alert goes to every channel set up.
CHOOSABLE_KINDS = tuple(kind for kind in AlertKind.values if kind != AlertKind.TEST)


# --- publishing (called by the domain apps and the watch) ------------------------------------


def alert_raise(
    *,
    owner: Owner,
    kind: str,
    subject: str,
    summary: str,
    detail: dict[str, object] | None = None,
    once: bool = False,
) -> Alert | None:
    """Tell `owner` of `kind` about `subject` by the channels the owner chose for it.

    With `once`, nothing is made while the same condition is open (alert_condition_resolve
    closes it): None then. Deliveries are queued when the caller's transaction commits.
    """
    if kind not in AlertKind.values:
        raise ValueError(f"unknown alert kind {kind!r}")
    with transaction.atomic():
        if once:
            try:
                with transaction.atomic():
                    AlertCondition.objects.create(owner=owner, kind=kind, subject=subject)
            except IntegrityError:
                return None  # alerted already in this episode
        alert = Alert.objects.create(
            owner=owner, kind=kind, subject=subject, summary=summary[:300], detail=detail or {}
        )
        deliveries = AlertDelivery.objects.bulk_create(_deliveries_for(alert))
        ids = [str(delivery.pk) for delivery in deliveries]
        transaction.on_commit(lambda: _deliveries_queue(ids))
    return alert


def _deliveries_for(alert: Alert) -> list[AlertDelivery]:
    preferences = alert_preferences_of(alert.owner)
    everything = alert.kind == AlertKind.TEST
    made = []
    verified = preferences.email and preferences.email_verified_at is not None
    if verified and (everything or alert.kind in preferences.email_kinds):
        made.append(
            AlertDelivery(
                alert=alert, channel=AlertDelivery.Channel.EMAIL, target=preferences.email
            )
        )
    if everything or alert.kind in preferences.webhook_kinds:
        made += [
            AlertDelivery(
                alert=alert, channel=AlertDelivery.Channel.WEBHOOK, endpoint=e, target=e.url
            )
            for e in webhook_endpoints_of(alert.owner)
        ]
    return made


def _deliveries_queue(ids: Sequence[str]) -> None:
    for delivery_id in ids:
        enqueue("alerts.tasks.alert_deliver", delivery_id)


def alert_condition_resolve(*, owner: Owner | int, kind: str, subject: str) -> bool:
    """The condition ended (the robot sent again, gas was topped up): the next one alerts."""
    owner_id = owner if isinstance(owner, int) else owner.pk
    return bool(
        AlertCondition.objects.filter(
            owner_id=owner_id, kind=kind, subject=subject, resolved_at__isnull=True
        ).update(resolved_at=timezone.now())
    )


def record_tampered_alert(
    *, owner: Owner, record_id: uuid.UUID, topic: str, robot: str, source: str
) -> Alert | None:
    """A record's stored ciphertext no longer matches the chain (once per record)."""
    return alert_raise(
        owner=owner,
        kind=AlertKind.RECORD_TAMPERED,
        subject=str(record_id),
        summary=f"Record {record_id} ({topic} from {robot}) was found tampered: its stored "
        "data no longer matches the digest on chain, and it is refused to every viewer.",
        detail={"record": str(record_id), "topic": topic, "robot": robot, "source": source},
        once=True,
    )


def anchoring_failed_alert(
    *, owner: Owner, record_ids: Sequence[uuid.UUID], reason: str, once: bool = False
) -> Alert | None:
    """Records of the owner could not be anchored (and will not be without an operator);
    with `once`, a second alert about the same records is not made."""
    if not record_ids:
        return None
    count = len(record_ids)
    first = str(record_ids[0])
    return alert_raise(
        owner=owner,
        kind=AlertKind.ANCHORING_FAILED,
        subject=first if count == 1 else f"{first} and {count - 1} more",
        summary=f"{count} record{'s' if count != 1 else ''} could not be anchored: {reason}",
        detail={
            "count": count,
            "records": [str(pk) for pk in record_ids[:RECORDS_LISTED]],
            "reason": reason,
        },
        once=once,
    )


def grant_received_alert(*, grantee: Owner, owner: Owner) -> Alert | None:
    """`owner`'s grant to `grantee` is confirmed on chain."""
    return alert_raise(
        owner=grantee,
        kind=AlertKind.GRANT_RECEIVED,
        subject=owner.user.username,
        summary=f"{owner.user.username} granted you access to their records.",
        detail={"granted_by": owner.user.username, "granted_by_eoa": owner.eoa_address},
    )


def grant_revoked_alert(*, grantee: Owner, owner: Owner) -> Alert | None:
    """`owner` took back `grantee`'s access (refused at once)."""
    return alert_raise(
        owner=grantee,
        kind=AlertKind.GRANT_REVOKED,
        subject=owner.user.username,
        summary=f"{owner.user.username} revoked your access to their records.",
        detail={"revoked_by": owner.user.username, "revoked_by_eoa": owner.eoa_address},
    )


def records_missing_subject(*, robot_id: uuid.UUID | str, signer: str, topic: str, gap: str) -> str:
    """The subject of one missing gap (`gap` is "from-to"): the robot, then a digest of the
    stream, at most 100 characters however long the topic."""
    stream = hashlib.sha256(f"{signer}\x00{topic}".encode()).hexdigest()[:16]
    return f"{robot_id}:{stream}:{gap}"[:100]


def records_missing_alert(
    *,
    owner: Owner,
    robot_id: uuid.UUID | str,
    robot: str,
    signer: str,
    topic: str,
    first: int,
    last: int,
) -> Alert | None:
    """Records `first`..`last` of a robot's stream (its key `signer`, one topic) are gone
    without a deletion that explains them: the portal has nothing for numbers the robot
    signed. Once per gap, ever (its condition stays open: the numbers do not come back)."""
    count = last - first + 1
    numbers = f"#{first}" if count == 1 else f"#{first} to #{last}"
    return alert_raise(
        owner=owner,
        kind=AlertKind.RECORDS_MISSING,
        subject=records_missing_subject(
            robot_id=robot_id, signer=signer, topic=topic, gap=f"{first}-{last}"
        ),
        summary=f"{count} record{'s' if count != 1 else ''} of {robot} missing on "
        f"{topic[:100]} ({numbers}): the robot sent and signed them, the portal holds nothing "
        "for them and no deletion explains it.",
        detail={
            "robot": str(robot_id),
            "name": robot,
            "topic": topic,
            "signer": signer,
            "from": first,
            "to": last,
        },
        once=True,
    )


def robot_key_disputed_alert(
    *,
    owner: Owner,
    robot_id: uuid.UUID | str,
    robot: str,
    key_hash: str,
    claimant_eoa: str,
    where: str,
) -> Alert | None:
    """Another account claims the key of the owner's robot: a pairing by another owner naming
    it was refused (`where` "pairing"), or the chain names that account as the key's first
    owner (`where` "chain"). Once per robot and `where`, ever."""
    if where == "chain":
        summary = (
            f"The chain names {claimant_eoa} as the first account to register the key of your "
            f"robot {robot}. The portal and authros-verify check your records against your own "
            "registration (robotKeyOfOwner) and still verify them; a verifier that reads only "
            "robotKeyOf would not. Pair the robot with a new key if you did not expect this."
        )
    else:
        summary = (
            f"Another owner ({claimant_eoa}) tried to pair a robot with the key of your robot "
            f"{robot}; the portal refused it. Your robot and its records are not affected."
        )
    return alert_raise(
        owner=owner,
        kind=AlertKind.ROBOT_KEY_DISPUTED,
        subject=f"{robot_id}:{where}",
        summary=summary,
        detail={
            "robot": str(robot_id),
            "name": robot,
            "key_hash": key_hash,
            "claimed_by": claimant_eoa,
            "where": where,
        },
        once=True,
    )


def alert_test_send(*, owner: Owner) -> Alert:
    """A test alert to every channel the owner set up, to check a receiver."""
    alert = alert_raise(
        owner=owner,
        kind=AlertKind.TEST,
        subject="test",
        summary="A test alert from the AuthROS portal: this channel works.",
    )
    assert alert is not None  # not `once`
    return alert


# --- the watch (beat) ------------------------------------------------------------------------


def alerts_watch() -> dict[str, int]:
    """The periodic checks: silent robots, low gas, deliveries whose message was lost."""
    return {
        **robots_silent_check(),
        **gas_low_check(),
        "deliveries_requeued": deliveries_requeue_stale(),
    }


def robots_silent_check(*, now: datetime | None = None) -> dict[str, int]:
    """Alert once for each robot silent beyond its owner's limit; close the condition of each
    robot that sent again (or is no longer watched)."""
    now = now or timezone.now()
    silent = robots_silent(now=now)
    raised = 0
    for one in silent:
        robot = one.robot
        since = one.silent_since.strftime("%Y-%m-%d %H:%M UTC")
        alert = alert_raise(
            owner=robot.owner,
            kind=AlertKind.ROBOT_SILENT,
            subject=str(robot.pk),
            summary=f"Robot {robot.name} has sent nothing since {since} "
            f"(you asked to be told after {one.minutes} minutes).",
            detail={"robot": str(robot.pk), "name": robot.name, "last_heard": since},
            once=True,
        )
        raised += alert is not None
    still = {(one.robot.owner_id, str(one.robot.pk)) for one in silent}
    resolved = 0
    for condition in alert_conditions_open(AlertKind.ROBOT_SILENT):
        if (condition.owner_id, condition.subject) not in still:
            resolved += alert_condition_resolve(
                owner=condition.owner_id, kind=AlertKind.ROBOT_SILENT, subject=condition.subject
            )
    return {"robots_silent": raised, "robots_back": resolved}


def gas_low_check() -> dict[str, int]:
    """Alert once while an owner's EOA holds less than the owner's threshold; close it when
    topped up. A chain that charges nothing for gas (fee 0, as `make run`'s anvil and a private
    PoA network) never alerts: an EOA there needs no ether, and holds none. A chain that does
    not answer skips this run."""
    raised = resolved = 0
    watching = owners_watching_gas()
    try:
        client = chain_client() if watching else None
        zero_gas = watching and client.fee_per_gas() == 0
        for preferences in watching:
            owner = preferences.owner
            balance = client.balance(owner.eoa_address)
            if zero_gas or balance >= preferences.gas_low_below_wei:
                resolved += alert_condition_resolve(
                    owner=owner, kind=AlertKind.GAS_LOW, subject=owner.eoa_address
                )
                continue
            threshold = preferences.gas_low_below_wei / WEI_PER_ETHER
            alert = alert_raise(
                owner=owner,
                kind=AlertKind.GAS_LOW,
                subject=owner.eoa_address,
                summary=f"Your account {owner.eoa_address} holds {_ether(balance)} ETH, below "
                f"the {_ether(preferences.gas_low_below_wei)} ETH you set: uploads and grants "
                "wait once it cannot pay for gas.",
                detail={
                    "eoa": owner.eoa_address,
                    "balance_wei": str(balance),
                    "threshold_ether": str(threshold),
                },
                once=True,
            )
            raised += alert is not None
    except ChainError as exc:
        logger.warning("the low-gas check skipped a run: the chain did not answer (%s)", exc)
    return {"gas_low": raised, "gas_topped_up": resolved}


def _ether(wei: int | Decimal) -> str:
    return f"{(Decimal(wei) / WEI_PER_ETHER).normalize():f}"


def deliveries_requeue_stale() -> int:
    """Queue again deliveries pending for longer than ALERTS_DELIVERY_STALE_AFTER (a lost
    message, a dead worker); receivers tell a repeat by its delivery id."""
    before = timezone.now() - timedelta(seconds=settings.ALERTS_DELIVERY_STALE_AFTER)
    stale = list(deliveries_stale(before=before).values_list("pk", flat=True))
    AlertDelivery.objects.filter(pk__in=stale).update(updated_at=timezone.now())
    _deliveries_queue([str(pk) for pk in stale])
    return len(stale)


# --- delivering (run by the worker) -----------------------------------------------------------


def alert_delivery_send(
    *, delivery_id: uuid.UUID | str, last_attempt: bool
) -> AlertDelivery | None:
    """One attempt to deliver. A failure a later attempt may cure raises DeliveryFailed (the
    task retries) unless this is the `last_attempt`; the delivery is then failed."""
    delivery = (
        AlertDelivery.objects.select_related("alert__owner__user", "endpoint")
        .filter(pk=delivery_id)
        .first()
    )
    if delivery is None or delivery.status != AlertDelivery.Status.PENDING:
        return delivery  # gone with its owner, or done by an earlier run
    delivery.attempts += 1
    try:
        if delivery.channel == AlertDelivery.Channel.EMAIL:
            _email_send(delivery)
        else:
            delivery.response_status = _webhook_send(delivery)
    except DeliveryFailed as exc:
        delivery.last_error = str(exc)[:300]
        if not last_attempt:
            delivery.save(update_fields=["attempts", "last_error", "response_status", "updated_at"])
            raise
        delivery.status = AlertDelivery.Status.FAILED
    except (WebhookUrlRefused, _Refused) as exc:
        delivery.last_error = str(exc)[:300]
        delivery.status = AlertDelivery.Status.FAILED
    else:
        delivery.status = AlertDelivery.Status.SENT
        delivery.sent_at = timezone.now()
        delivery.last_error = ""
    delivery.save()
    return delivery


class _Refused(Exception):
    """An answer another attempt would get again (a redirect, a 4xx): no retry."""


def _email_send(delivery: AlertDelivery) -> None:
    alert = delivery.alert
    title = AlertKind(alert.kind).label
    lines = [alert.summary, ""]
    lines += [f"{key}: {value}" for key, value in alert.detail.items()]
    lines += ["", f"When: {alert.created_at:%Y-%m-%d %H:%M:%S} UTC", f"Alert id: {alert.pk}"]
    if settings.ALERTS_PORTAL_URL:
        lines.append(
            f"Your alert settings: {settings.ALERTS_PORTAL_URL.rstrip('/')}/account/alerts/"
        )
    message = EmailMessage(
        subject=f"[AuthROS] {title}",
        body="\n".join(lines) + "\n",
        from_email=settings.DEFAULT_FROM_EMAIL,
        to=[delivery.target],
        headers={"X-AuthROS-Alert": str(alert.pk), "X-AuthROS-Event": alert.kind},
    )
    try:
        message.send(fail_silently=False)
    except OSError as exc:  # smtplib.SMTPException is an OSError
        raise DeliveryFailed(f"the mail server refused or did not answer: {exc}") from None


def alert_payload(alert: Alert, *, delivery_id: uuid.UUID | str) -> bytes:
    """The webhook body (docs/alerts.md): compact JSON, signed byte for byte."""
    payload = {
        "id": str(alert.pk),
        "delivery": str(delivery_id),
        "type": alert.kind,
        "owner": alert.owner.user.username,
        "subject": alert.subject,
        "summary": alert.summary,
        "detail": alert.detail,
        "created_at": alert.created_at.isoformat().replace("+00:00", "Z"),
    }
    return json.dumps(payload, separators=(",", ":"), sort_keys=True).encode()


def _webhook_send(delivery: AlertDelivery) -> int:
    endpoint = delivery.endpoint
    if endpoint is None:
        raise _Refused("the endpoint was deleted")
    body = alert_payload(delivery.alert, delivery_id=delivery.pk)
    timestamp = int(time.time())
    secret = unwrap(bytes(endpoint.secret_wrapped), purpose=_secret_purpose(endpoint.pk)).decode()
    answer = webhook_post(
        url=endpoint.url,
        body=body,
        headers={
            "Content-Type": "application/json",
            "User-Agent": "AuthROS-Webhooks/1",
            "X-AuthROS-Event": delivery.alert.kind,
            "X-AuthROS-Delivery": str(delivery.pk),
            "X-AuthROS-Timestamp": str(timestamp),
            "X-AuthROS-Signature": webhook_signature(secret=secret, timestamp=timestamp, body=body),
        },
    )
    delivery.response_status = answer.status
    if 200 <= answer.status < 300:
        return answer.status
    said = f"the receiver answered {answer.status}"
    if answer.start.strip():
        said += f" ({' '.join(answer.start.split())[:100]})"
    if 300 <= answer.status < 400:
        raise _Refused(f"{said} (a redirect, not followed): give the final URL")
    if answer.status in (408, 429) or answer.status >= 500:
        raise DeliveryFailed(said)
    raise _Refused(said)


# --- the owner's settings ---------------------------------------------------------------------


def alert_preferences_update(
    *,
    owner: Owner,
    email: str,
    email_kinds: Sequence[str],
    webhook_kinds: Sequence[str],
    robot_silent_minutes: int | None,
    gas_low_below_wei: int | None,
    verify_url: str = "",
) -> AlertPreferences:
    """Save the owner's choices; InvalidAlertPreferences (and nothing saved) when they do not
    hold together. A new address gets a link to confirm it (`verify_url` is the absolute URL
    of the verification page, the token appended); e-mail goes there once it is confirmed."""
    unknown = set(email_kinds) | set(webhook_kinds)
    unknown -= set(CHOOSABLE_KINDS)
    if unknown:
        raise InvalidAlertPreferences(f"unknown alert kinds: {', '.join(sorted(unknown))}")
    if email_kinds and not email:
        raise InvalidAlertPreferences("give an e-mail address for the alerts sent by e-mail")
    chosen = set(email_kinds) | set(webhook_kinds)
    if AlertKind.ROBOT_SILENT in chosen and robot_silent_minutes is None:
        raise InvalidAlertPreferences("say after how many minutes a silent robot is reported")
    if robot_silent_minutes is not None and not (
        ROBOT_SILENT_MINUTES_MIN <= robot_silent_minutes <= ROBOT_SILENT_MINUTES_MAX
    ):
        raise InvalidAlertPreferences(
            f"a robot is silent after {ROBOT_SILENT_MINUTES_MIN} to {ROBOT_SILENT_MINUTES_MAX} "
            "minutes"
        )
    if AlertKind.GAS_LOW in chosen and gas_low_below_wei is None:
        raise InvalidAlertPreferences("say below which balance your account is low on gas")
    if gas_low_below_wei is not None and gas_low_below_wei <= 0:
        raise InvalidAlertPreferences("the low-gas threshold is above zero")
    ordered = [kind for kind in CHOOSABLE_KINDS]
    before = alert_preferences_of(owner)
    unchanged = before.pk is not None and before.email == email
    verified_at = before.email_verified_at if unchanged else None
    preferences, _ = AlertPreferences.objects.update_or_create(
        owner=owner,
        defaults={
            "email": email,
            "email_verified_at": verified_at,
            "email_kinds": [kind for kind in ordered if kind in email_kinds],
            "webhook_kinds": [kind for kind in ordered if kind in webhook_kinds],
            "robot_silent_minutes": robot_silent_minutes,
            "gas_low_below_wei": gas_low_below_wei,
        },
    )
    if email and verified_at is None:
        transaction.on_commit(
            lambda: enqueue("alerts.tasks.email_verification_send", owner.pk, verify_url)
        )
    return preferences


EMAIL_LINK_SALT = "alerts.email-verification"
EMAIL_LINK_MAX_AGE = 3 * 24 * 3600


def email_verification_send(*, owner_id: int, verify_url: str) -> bool:
    """Send the owner's alert address a link that proves it is theirs (`verify_url` + a signed
    token of the owner and the address); False if there is nothing to verify any more."""
    preferences = AlertPreferences.objects.filter(owner_id=owner_id).first()
    if preferences is None or not preferences.email or preferences.email_verified_at:
        return False
    token = signing.dumps({"o": owner_id, "e": preferences.email}, salt=EMAIL_LINK_SALT)
    message = EmailMessage(
        subject="[AuthROS] Confirm your address for alerts",
        body="Someone (you, we hope) asked the AuthROS portal to send alerts of the account "
        f"{preferences.owner.user.username} to this address. Open this link, signed in, to "
        f"confirm it (it works for 3 days):\n\n{verify_url}{token}/\n\n"
        "If it was not you, ignore this message: nothing is sent here unless you confirm.\n",
        from_email=settings.DEFAULT_FROM_EMAIL,
        to=[preferences.email],
    )
    try:
        message.send(fail_silently=False)
    except OSError as exc:
        raise DeliveryFailed(f"the mail server refused or did not answer: {exc}") from None
    return True


def alert_email_verify(*, owner: Owner, token: str) -> AlertPreferences:
    """Mark the owner's alert address verified by the link's token; EmailLinkInvalid if the
    token is not this owner's current address's, or too old."""
    try:
        signed = signing.loads(token, salt=EMAIL_LINK_SALT, max_age=EMAIL_LINK_MAX_AGE)
    except signing.SignatureExpired:
        raise EmailLinkInvalid(
            "this link has expired: save your settings to get a new one"
        ) from None
    except signing.BadSignature:
        raise EmailLinkInvalid("this link is not valid") from None
    preferences = AlertPreferences.objects.filter(owner=owner).first()
    if (
        not isinstance(signed, dict)
        or signed.get("o") != owner.pk
        or preferences is None
        or signed.get("e") != preferences.email
    ):
        raise EmailLinkInvalid("this link is for another account or an address changed since")
    if preferences.email_verified_at is None:
        preferences.email_verified_at = timezone.now()
        preferences.save(update_fields=["email_verified_at", "updated_at"])
    return preferences


def webhook_endpoint_create(*, owner: Owner, url: str) -> tuple[WebhookEndpoint, str]:
    """A new endpoint and its signing secret, returned once (it is kept wrapped, never shown
    again). WebhookUrlRefused for a URL the portal will not POST to."""
    url = url.strip()
    webhook_url_check(url)
    with transaction.atomic():
        # One owner's endpoints are counted under a lock on the owner's row.
        Owner.objects.select_for_update().filter(pk=owner.pk).first()
        if webhook_endpoints_of(owner).count() >= settings.ALERTS_WEBHOOKS_PER_OWNER:
            raise TooManyWebhooks(
                f"at most {settings.ALERTS_WEBHOOKS_PER_OWNER} webhooks: delete one first"
            )
        secret = WEBHOOK_SECRET_PREFIX + secrets.token_urlsafe(32)
        endpoint = WebhookEndpoint(owner=owner, url=url, secret_prefix=secret[:10])
        endpoint.secret_wrapped = wrap(secret.encode(), purpose=_secret_purpose(endpoint.pk))
        endpoint.save()
    return endpoint, secret


def webhook_endpoint_delete(*, endpoint: WebhookEndpoint) -> None:
    """Stop sending there; its deliveries stay in the log."""
    endpoint.delete()


def _secret_purpose(endpoint_id: uuid.UUID) -> str:
    return f"webhook-secret:{endpoint_id}"
