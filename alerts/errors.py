"""What the alerts services refuse, as values the caller can act on."""

from core.errors import DomainError


class AlertError(DomainError):
    code = "alert_error"
    http_status = 400


class WebhookUrlRefused(AlertError):
    """A URL the portal will not POST to (a private address, not http(s), unresolvable)."""

    code = "webhook_url_refused"


class TooManyWebhooks(AlertError):
    code = "too_many_webhooks"


class InvalidAlertPreferences(AlertError):
    code = "invalid_alert_preferences"


class DeliveryFailed(Exception):
    """One attempt to deliver failed in a way a later attempt may not (retried by the task)."""


class EmailLinkInvalid(AlertError):
    """A verification link that is not this owner's, has expired, or names another address."""

    code = "email_link_invalid"
