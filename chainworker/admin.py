"""Admin console for deployments, and the chain status page (linked from the admin index)."""

from decimal import Decimal

from django.conf import settings
from django.contrib import admin
from django.core.exceptions import PermissionDenied
from django.http import HttpRequest, HttpResponse
from django.template.response import TemplateResponse
from django.urls import URLPattern, path
from redis.exceptions import RedisError

from chainworker.backlog import backlog_counts
from chainworker.errors import ChainError
from chainworker.gas import LowBalance, low_balances
from chainworker.models import Deployment, OperatorAlert
from chainworker.services import chain_status, operator_gas
from core.redis_client import redis_client
from core.redis_url import RedisUrlError, redis_target

WEI_PER_ETHER = Decimal(10) ** 18
# Kombu's Redis transport keeps messages of priority p > 0 under "<queue>\x06\x16<p>".
KOMBU_PRIORITY_SEPARATOR = "\x06\x16"
KOMBU_PRIORITY_STEPS = (3, 6, 9)


@admin.register(Deployment)
class DeploymentAdmin(admin.ModelAdmin):
    """Read-only: the active deployment is the contract every record is checked against, so
    whoever could change or delete it here could make the portal call a record genuine.
    `manage.py chain_deploy` deploys and records."""

    list_display = ("address", "chain_id", "block_number", "is_active", "created_at")
    list_filter = ("is_active", "chain_id")
    search_fields = ("address", "tx_hash", "deployer")
    readonly_fields = [f.name for f in Deployment._meta.fields]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: Deployment | None = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: Deployment | None = None) -> bool:
        return False

    def get_urls(self) -> list[URLPattern]:
        status_view = self.admin_site.admin_view(self.chain_status_view)
        return [path("chain-status/", status_view, name="chain-status"), *super().get_urls()]

    def chain_status_view(self, request: HttpRequest) -> HttpResponse:
        if not request.user.has_perm("chainworker.view_deployment"):
            raise PermissionDenied
        try:
            status = chain_status()
            problem = status.get("problem")
        except ChainError as exc:
            status, problem = None, f"The chain node is not reachable: {exc}"
        balance, operator_low, low_accounts = None, False, None
        if status is not None:
            balance = Decimal(int(status["operator_balance_wei"])) / WEI_PER_ETHER
            try:
                operator_low = operator_gas().low
                low_accounts = [_in_ether(low) for low in low_balances()]
            except ChainError:
                pass  # the node went away meanwhile: the lists say "unavailable"
        context = {
            **self.admin_site.each_context(request),
            "title": "Chain status",
            "status": status,
            "problem": problem,
            "operator_balance": balance,
            "operator_low": operator_low,
            "operator_low_ether": Decimal(settings.CHAIN_OPERATOR_LOW_WEI) / WEI_PER_ETHER,
            "low_accounts": low_accounts,
            "alerts": OperatorAlert.objects.filter(resolved_at=None),
            "queue_name": settings.CELERY_TASK_DEFAULT_QUEUE,
            "queue_length": celery_queue_length(),
            "pending": backlog_counts(),
            "deployments": Deployment.objects.filter(is_active=True),
        }
        status_code = 200 if status is not None else 503
        return TemplateResponse(request, "admin/chain_status.html", context, status=status_code)


@admin.register(OperatorAlert)
class OperatorAlertAdmin(admin.ModelAdmin):
    """Read-only: alerts are raised and resolved by the chain work that meets their cause."""

    list_display = ("kind", "subject", "created_at", "last_seen_at", "resolved_at")
    list_filter = ("kind", ("resolved_at", admin.EmptyFieldListFilter))
    search_fields = ("kind", "subject")
    readonly_fields = [f.name for f in OperatorAlert._meta.fields]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: OperatorAlert | None = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: OperatorAlert | None = None) -> bool:
        return False


def _in_ether(low: LowBalance) -> dict[str, object]:
    return {
        "label": low.label,
        "address": low.address,
        "balance": Decimal(low.balance_wei) / WEI_PER_ETHER,
        "below": Decimal(low.below_wei) / WEI_PER_ETHER,
    }


def celery_queue_length() -> int | None:
    """Messages waiting in the Celery queue on a Redis broker (plain or behind Sentinels); None
    if it cannot be read."""
    try:
        redis_target(settings.BROKER_REDIS_URL)
    except RedisUrlError:
        return None  # not a Redis broker
    queue = settings.CELERY_TASK_DEFAULT_QUEUE
    keys = [queue, *(f"{queue}{KOMBU_PRIORITY_SEPARATOR}{p}" for p in KOMBU_PRIORITY_STEPS)]
    try:
        client = redis_client(settings.BROKER_REDIS_URL)
        return sum(int(client.llen(key)) for key in keys)
    except RedisError:
        return None
