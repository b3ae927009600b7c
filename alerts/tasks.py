"""Celery tasks of alerts: a delivery (retried with backoff) and the periodic watch."""

from celery import shared_task
from django.conf import settings

from alerts import services
from alerts.errors import DeliveryFailed

# A receiver down for a while is tried again after 2, 4, 8 ... seconds, at most
# ALERTS_RETRY_BACKOFF_MAX apart, ALERTS_DELIVERY_MAX_RETRIES times; then the delivery is failed
# (the owner sees it in the log). Late acks: a worker killed mid-delivery delivers again.
DELIVERY_TASK = {
    "autoretry_for": (DeliveryFailed,),
    "retry_backoff": 2,
    "retry_backoff_max": settings.ALERTS_RETRY_BACKOFF_MAX,
    "retry_jitter": True,
    "max_retries": settings.ALERTS_DELIVERY_MAX_RETRIES,
    "acks_late": True,
    "soft_time_limit": 60,
    "time_limit": 90,
}


@shared_task(bind=True, name="alerts.tasks.alert_deliver", **DELIVERY_TASK)
def alert_deliver(self, delivery_id: str) -> str | None:
    last_attempt = self.request.retries >= self.max_retries
    delivery = services.alert_delivery_send(delivery_id=delivery_id, last_attempt=last_attempt)
    return delivery.status if delivery else None


@shared_task(name="alerts.tasks.email_verification_send", **DELIVERY_TASK)
def email_verification_send(owner_id: int, verify_url: str) -> bool:
    return services.email_verification_send(owner_id=owner_id, verify_url=verify_url)


# Periodic (beat): the next run repeats what a failed one did not do, so it is never retried.
@shared_task(name="alerts.tasks.alerts_watch", soft_time_limit=120, time_limit=150)
def alerts_watch() -> dict[str, int]:
    return services.alerts_watch()
