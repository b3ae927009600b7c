"""Admin console for deployments, and the chain status page (linked from the admin index)."""

from decimal import Decimal

import redis
from django.conf import settings
from django.contrib import admin
from django.core.exceptions import PermissionDenied
from django.http import HttpRequest, HttpResponse
from django.template.response import TemplateResponse
from django.urls import URLPattern, path
from redis.exceptions import RedisError

from chainworker.backlog import backlog_counts
from chainworker.chain import ChainError
from chainworker.models import Deployment
from chainworker.services import chain_status
from core.redis_client import get_redis

WEI_PER_ETHER = Decimal(10) ** 18
# Kombu's Redis transport keeps messages of priority p > 0 under "<queue>\x06\x16<p>".
KOMBU_PRIORITY_SEPARATOR = "\x06\x16"
KOMBU_PRIORITY_STEPS = (3, 6, 9)


@admin.register(Deployment)
class DeploymentAdmin(admin.ModelAdmin):
    list_display = ("address", "chain_id", "block_number", "is_active", "created_at")
    list_filter = ("is_active", "chain_id")
    search_fields = ("address", "tx_hash", "deployer")
    readonly_fields = [f.name for f in Deployment._meta.fields]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False  # `manage.py chain_deploy` deploys and records

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
        balance = None
        if status is not None:
            balance = Decimal(int(status["operator_balance_wei"])) / WEI_PER_ETHER
        context = {
            **self.admin_site.each_context(request),
            "title": "Chain status",
            "status": status,
            "problem": problem,
            "operator_balance": balance,
            "queue_name": settings.CELERY_TASK_DEFAULT_QUEUE,
            "queue_length": celery_queue_length(),
            "pending": backlog_counts(),
            "deployments": Deployment.objects.filter(is_active=True),
        }
        status_code = 200 if status is not None else 503
        return TemplateResponse(request, "admin/chain_status.html", context, status=status_code)


def celery_queue_length() -> int | None:
    """Messages waiting in the Celery queue on a Redis broker; None if it cannot be read."""
    broker_url = settings.CELERY_BROKER_URL
    if not broker_url.startswith(("redis://", "rediss://", "unix://")):
        return None
    queue = settings.CELERY_TASK_DEFAULT_QUEUE
    keys = [queue, *(f"{queue}{KOMBU_PRIORITY_SEPARATOR}{p}" for p in KOMBU_PRIORITY_STEPS)]
    try:
        client = (
            get_redis()
            if broker_url == settings.REDIS_URL
            else redis.Redis.from_url(broker_url, socket_timeout=5, socket_connect_timeout=5)
        )
        return sum(int(client.llen(key)) for key in keys)
    except RedisError:
        return None
