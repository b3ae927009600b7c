"""Settings for the AuthROS portal: the one place that reads the environment.

Every deployment knob is an environment variable (or a line in a `.env` file beside
manage.py); docs/operations.md lists them. Secrets that are not given in the environment
are created on first use as 0600 files under AUTHROS_VAR_DIR, never in the database.
"""

import os
from datetime import timedelta
from pathlib import Path

import environ
from django.core.exceptions import ImproperlyConfigured
from kombu import Queue

from core.logging import logging_config
from core.rates import rate_parse
from core.redis_url import celery_redis, redis_target
from core.secrets import load_or_create_secret
from core.storage_url import envelope_storage_config

BASE_DIR = Path(__file__).resolve().parent.parent

env = environ.Env()
environ.Env.read_env(BASE_DIR / ".env", overwrite=False)

VAR_DIR = Path(env.str("AUTHROS_VAR_DIR", default=str(BASE_DIR / "var")))
SECRETS_DIR = Path(env.str("AUTHROS_SECRETS_DIR", default=str(VAR_DIR / "secrets")))

DEBUG = env.bool("DJANGO_DEBUG", default=False)
SECRET_KEY = env.str("DJANGO_SECRET_KEY", default="") or (
    load_or_create_secret(SECRETS_DIR / "django-secret-key", nbytes=32).hex()
)
ALLOWED_HOSTS = env.list("DJANGO_ALLOWED_HOSTS", default=["localhost", "127.0.0.1", "[::1]"])
CSRF_TRUSTED_ORIGINS = env.list("DJANGO_CSRF_TRUSTED_ORIGINS", default=[])

HTTPS = env.bool("AUTHROS_HTTPS", default=False)
SESSION_COOKIE_SECURE = HTTPS
CSRF_COOKIE_SECURE = HTTPS
SECURE_SSL_REDIRECT = HTTPS
SECURE_HSTS_SECONDS = 31536000 if HTTPS else 0
SECURE_PROXY_SSL_HEADER = ("HTTP_X_FORWARDED_PROTO", "https") if HTTPS else None
SESSION_COOKIE_HTTPONLY = True
SESSION_COOKIE_SAMESITE = "Lax"
CSRF_COOKIE_SAMESITE = "Lax"
X_FRAME_OPTIONS = "DENY"
SECURE_CONTENT_TYPE_NOSNIFF = True
SECURE_REFERRER_POLICY = "same-origin"
# Content-Security-Policy of every response (portal.middleware.ContentSecurityPolicyMiddleware):
# scripts and styles only from the portal's own static files (no inline script, no on*=
# handler, no style attribute: the pages run SM2 on the owner's key), images also as data:
# URLs (a record's verified image), no plugins, no <base>, no framing, forms only to the
# portal. Violations are reported to CSP_REPORT_URL (portal.csp_reports).
CSP_DIRECTIVES = {
    "default-src": ["'self'"],
    "script-src": ["'self'"],
    "style-src": ["'self'"],
    "img-src": ["'self'", "data:"],
    "object-src": ["'none'"],
    "base-uri": ["'none'"],
    "frame-ancestors": ["'none'"],
    "form-action": ["'self'"],
}
CSP_REPORT_URL = "/csp-report/"

INSTALLED_APPS = [
    "django.contrib.admin",
    "django.contrib.auth",
    "django.contrib.contenttypes",
    "django.contrib.sessions",
    "django.contrib.messages",
    "django.contrib.staticfiles",
    "rest_framework",
    "drf_spectacular",
    "drf_spectacular_sidecar",
    "axes",
    "accounts",
    "sharing",
    "alerts",
    "chainworker",
]

MIDDLEWARE = [
    # First: the probes (/healthz, /readyz, /metrics) are answered here, before any other
    # middleware (no host check, session, redirect or service check); every other request gets
    # its id, log context, access line and metrics.
    "portal.request_context.RequestContextMiddleware",
    "django.middleware.security.SecurityMiddleware",
    # The Content-Security-Policy header on every answer, the 503s and static files included.
    "portal.middleware.ContentSecurityPolicyMiddleware",
    # Serves /static/ from the portal itself, so pages work without DEBUG and without a proxy.
    "whitenoise.middleware.WhiteNoiseMiddleware",
    # 503 for everything but /static/ while the portal's own secrets or operator key are wrong.
    "portal.middleware.ServiceChecksMiddleware",
    "django.contrib.sessions.middleware.SessionMiddleware",
    "django.middleware.common.CommonMiddleware",
    "django.middleware.csrf.CsrfViewMiddleware",
    "django.contrib.auth.middleware.AuthenticationMiddleware",
    "django.contrib.messages.middleware.MessageMiddleware",
    "django.middleware.clickjacking.XFrameOptionsMiddleware",
    # Last, as django-axes asks: it locks out repeated failed logins.
    "axes.middleware.AxesMiddleware",
]

AUTHENTICATION_BACKENDS = [
    "axes.backends.AxesStandaloneBackend",
    "django.contrib.auth.backends.ModelBackend",
]

ROOT_URLCONF = "portal.urls"
WSGI_APPLICATION = "portal.wsgi.application"

TEMPLATES = [
    {
        "BACKEND": "django.template.backends.django.DjangoTemplates",
        "DIRS": [BASE_DIR / "templates"],
        "APP_DIRS": True,
        "OPTIONS": {
            "context_processors": [
                "django.template.context_processors.request",
                "django.contrib.auth.context_processors.auth",
                "django.contrib.messages.context_processors.messages",
            ],
        },
    },
]

DATABASES = {
    "default": env.db("DATABASE_URL", default=f"sqlite:///{VAR_DIR / 'db.sqlite3'}"),
}
# Persistent connections: a new one per request costs more than the request (SQLite's PRAGMAs,
# PostgreSQL's connection set-up). Each web thread and worker process keeps one; with a
# pooler (PgBouncer, transaction mode) in front set DATABASE_CONN_MAX_AGE=0.
DATABASES["default"]["CONN_MAX_AGE"] = env.int("DATABASE_CONN_MAX_AGE", default=60)
DATABASES["default"]["CONN_HEALTH_CHECKS"] = True
if DATABASES["default"]["ENGINE"] == "django.db.backends.sqlite3":
    # Several processes (web, workers) share the file: WAL, and take the write lock up front.
    DATABASES["default"].setdefault("OPTIONS", {}).update(
        {
            "init_command": "PRAGMA journal_mode=WAL; PRAGMA synchronous=NORMAL;",
            "transaction_mode": "IMMEDIATE",
            "timeout": 30,
        }
    )
# One test database per test run, so that two runs on one machine never share one; for
# SQLite a file, not memory, so that worker processes started by the tests see the test data.
if DATABASES["default"]["ENGINE"] == "django.db.backends.sqlite3":
    DATABASES["default"]["TEST"] = {"NAME": str(VAR_DIR / f"test-db-{os.getpid()}.sqlite3")}
else:
    DATABASES["default"]["TEST"] = {"NAME": f"test_{DATABASES['default']['NAME']}_{os.getpid()}"}
DEFAULT_AUTO_FIELD = "django.db.models.BigAutoField"

# A plain Redis, Sentinels (sentinel://H:P,H:P/DB?master=NAME) or a Cluster
# (redis+cluster://H:P,H:P): core/redis_url.py. A URL it cannot read stops every process here.
REDIS_URL = env.str("REDIS_URL", default="redis://127.0.0.1:6379/0")
_REDIS = redis_target(REDIS_URL)
# Every key the portal writes starts with this, so several portals can share one Redis.
REDIS_KEY_PREFIX = env.str("REDIS_KEY_PREFIX", default="authros")
CACHES = {
    "default": {
        "BACKEND": "core.redis_client.SharedRedisCache",
        "LOCATION": REDIS_URL,
        "KEY_PREFIX": REDIS_KEY_PREFIX,
    },
}

AUTH_PASSWORD_VALIDATORS = [
    {"NAME": "django.contrib.auth.password_validation.UserAttributeSimilarityValidator"},
    {"NAME": "django.contrib.auth.password_validation.MinimumLengthValidator"},
    {"NAME": "django.contrib.auth.password_validation.CommonPasswordValidator"},
    {"NAME": "django.contrib.auth.password_validation.NumericPasswordValidator"},
]

LANGUAGE_CODE = "en-us"
TIME_ZONE = "UTC"
USE_I18N = True
USE_TZ = True

STATIC_URL = "static/"
# Only for `collectstatic` (e.g. to put the files behind a CDN); WhiteNoise serves the sources.
STATIC_ROOT = env.str("STATIC_ROOT", default="") or None
STATICFILES_DIRS = [BASE_DIR / "static"]
# Serve straight from the source folders: no `collectstatic` step to forget.
WHITENOISE_USE_FINDERS = True
MEDIA_ROOT = Path(env.str("AUTHROS_MEDIA_ROOT", default=str(VAR_DIR / "media")))

# --- Chain -------------------------------------------------------------------------------
# The JSON-RPC endpoint of the chain node: http(s)://host:port.
CHAIN_RPC_URL = env.str("CHAIN_RPC_URL", default="http://127.0.0.1:8545")
# The chain node's URL as the portal's users reach it, printed in the verify command of an
# export's page; the portal's own by default (`make run`'s anvil, on this machine).
PUBLIC_RPC_URL = env.str("PUBLIC_RPC_URL", default=CHAIN_RPC_URL)
# Optional pin; otherwise the address recorded by `manage.py chain_deploy` is used.
CHAIN_CONTRACT_ADDRESS = env.str("CHAIN_CONTRACT_ADDRESS", default="")
# Hex private key of the operator (contract admin, funds new EOAs); else a 0600 file.
CHAIN_OPERATOR_KEY = env.str("CHAIN_OPERATOR_KEY", default="")
CHAIN_RECEIPT_TIMEOUT = env.float("CHAIN_RECEIPT_TIMEOUT", default=120.0)
CHAIN_RPC_TIMEOUT = env.float("CHAIN_RPC_TIMEOUT", default=10.0)
CHAIN_CONFIRMATIONS = env.int("CHAIN_CONFIRMATIONS", default=0)
# Seconds a sender's nonce lock outlives a process that died holding it.
CHAIN_NONCE_LOCK_TIMEOUT = env.float("CHAIN_NONCE_LOCK_TIMEOUT", default=15.0)
# Each new custodial EOA gets CHAIN_EOA_FUNDING_GAS gas units at the chain's current max fee
# per gas (registration plus a working allowance of uploads), at most CHAIN_EOA_FUNDING_WEI;
# nothing on a chain whose gas price and base fee are zero.
CHAIN_EOA_FUNDING_GAS = env.int("CHAIN_EOA_FUNDING_GAS", default=20_000_000)
CHAIN_EOA_FUNDING_WEI = env.int("CHAIN_EOA_FUNDING_WEI", default=10**18)
# At most this much wei goes to new EOAs per SIGNUP_FUNDING_PERIOD seconds; registrations
# past it wait (pending) until the period frees some.
SIGNUP_FUNDING_BUDGET_WEI = env.int("SIGNUP_FUNDING_BUDGET_WEI", default=50 * 10**18)
SIGNUP_FUNDING_PERIOD = env.float("SIGNUP_FUNDING_PERIOD", default=24 * 3600.0)
# An owner's EOA holding less than CHAIN_EOA_TOPUP_BELOW_GAS gas units at the current max fee
# per gas is topped up to CHAIN_EOA_TOPUP_GAS gas units (capped by CHAIN_EOA_FUNDING_WEI),
# within the same funding budget; nothing on a zero-gas chain.
CHAIN_EOA_TOPUP_BELOW_GAS = env.int("CHAIN_EOA_TOPUP_BELOW_GAS", default=2_000_000)
CHAIN_EOA_TOPUP_GAS = env.int("CHAIN_EOA_TOPUP_GAS", default=CHAIN_EOA_FUNDING_GAS)
# The admin warns (and an operator alert is raised) when the operator holds less than this
# on a chain with gas prices.
CHAIN_OPERATOR_LOW_WEI = env.int("CHAIN_OPERATOR_LOW_WEI", default=10**18)
# Registrations (page POSTs that would create an owner) per client address and overall,
# counted in Redis across web processes: "<count>/<second|minute|hour|day>".
SIGNUP_RATE_PER_ADDRESS = env.str("SIGNUP_RATE_PER_ADDRESS", default="5/hour")
SIGNUP_RATE_TOTAL = env.str("SIGNUP_RATE_TOTAL", default="200/hour")
# New owners wait for an operator's approval (admin) before any chain work is done for them.
SIGNUP_APPROVAL = env.bool("SIGNUP_APPROVAL", default=False)
# Seconds a robot's pairing request waits for its owner's answer before it expires.
ROBOT_PAIRING_TTL = env.int("ROBOT_PAIRING_TTL", default=900)
# An envelope sealed under a retired key is accepted when captured before the rotation, give or
# take this many seconds of robot clock (sharing.services.uploads._UploadKeys).
KEY_ROTATION_CLOCK_SKEW = env.float("KEY_ROTATION_CLOCK_SKEW", default=300.0)
# On a development chain (anvil) the operator is topped up automatically.
CHAIN_DEV_FAUCET = env.bool("CHAIN_DEV_FAUCET", default=True)

# Portal master key (KEK, 32 hex digits = SM4 key) wrapping owner keys; else a 0600 file.
AUTHROS_MASTER_KEY = env.str("AUTHROS_MASTER_KEY", default="")
# The portal's SM2 private key (64 hex digits) for the key exchange; else a 0600 file.
AUTHROS_SM2_PRIVATE_KEY = env.str("AUTHROS_SM2_PRIVATE_KEY", default="")
# Seconds between checks of the master key and the operator key while they fail (the portal
# answers 503 meanwhile) or while the chain does not answer (portal/middleware.py).
SERVICE_CHECK_INTERVAL = env.float("SERVICE_CHECK_INTERVAL", default=30.0)
# Seconds the chain's latest block is reused by the identity check (a burst of requests
# costs one call); the commitment on chain is kept per owner and block.
IDENTITY_BLOCK_CACHE_SECONDS = env.float("IDENTITY_BLOCK_CACHE_SECONDS", default=1.0)

LOGIN_URL = "login"
LOGIN_REDIRECT_URL = "dashboard"
LOGOUT_REDIRECT_URL = "login"

# --- Login throttling (django-axes) -------------------------------------------------------
AXES_ENABLED = env.bool("AXES_ENABLED", default=True)
AXES_FAILURE_LIMIT = env.int("AXES_FAILURE_LIMIT", default=5)
AXES_COOLOFF_TIME = env.float("AXES_COOLOFF_HOURS", default=0.25)
AXES_LOCKOUT_PARAMETERS = [["username", "ip_address"]]
AXES_RESET_ON_SUCCESS = True
# Whose address a failed sign-in counts against: the one the API throttles use, with the same
# proxy count (REST_FRAMEWORK NUM_PROXIES, from API_NUM_PROXIES). With 0 only the peer address
# counts, so a client cannot pick another address by sending X-Forwarded-For; behind a proxy
# it is the address that proxy appended. (django-axes' own AXES_IPWARE_* settings need
# django-ipware, which is not installed: without it axes would see only the proxy's address.)
AXES_CLIENT_IP_CALLABLE = "accounts.views.client_ip_address"

# --- Page rate limits (accounts.decorators.page_throttle) ---------------------------------
# Per signed-in user, counted in Redis across web processes: "<count>/<second|minute|hour|day>"
# (empty: no limit). Every page counts 1 against PAGE_RATE_USER; what a page's integrity checks
# cost is CHECK_BUDGET's.
PAGE_RATE_USER = env.str("PAGE_RATE_USER", default="600/minute")
# Records one caller (owner or grantee; an owner API token's calls are its owner's) may have
# checked against the chain, pages and API alike, "<records>/<period>" (empty: no budget):
# spent at once if need be, refilled evenly over the period (sharing/verification/budget.py).
# 20,000 a minute holds a 30-minute plot of a 10 Hz topic (18,000 records) and its refreshes.
CHECK_BUDGET = env.str("CHECK_BUDGET", default="20000/minute")
try:
    if CHECK_BUDGET and rate_parse(CHECK_BUDGET)[0] < 1:
        raise ValueError("a budget of no records refuses every read; leave it empty for none")
except ValueError as exc:
    raise ImproperlyConfigured(f"CHECK_BUDGET: {exc}") from None

# --- REST API (DRF, drf-spectacular) ------------------------------------------------------
REST_FRAMEWORK = {
    "DEFAULT_AUTHENTICATION_CLASSES": [
        # Owner API tokens first: a key that is none is left to the robot tokens.
        "accounts.authentication.OwnerTokenAuthentication",
        "accounts.authentication.RobotTokenAuthentication",
        "rest_framework.authentication.SessionAuthentication",
    ],
    "DEFAULT_PERMISSION_CLASSES": ["rest_framework.permissions.IsAuthenticated"],
    "DEFAULT_PARSER_CLASSES": ["rest_framework.parsers.JSONParser"],
    "DEFAULT_RENDERER_CLASSES": ["rest_framework.renderers.JSONRenderer"],
    "DEFAULT_CONTENT_NEGOTIATION_CLASS": "core.api_negotiation.JsonContentNegotiation",
    "DEFAULT_SCHEMA_CLASS": "drf_spectacular.openapi.AutoSchema",
    "EXCEPTION_HANDLER": "core.api_errors.exception_handler",
    "DEFAULT_PAGINATION_CLASS": "rest_framework.pagination.LimitOffsetPagination",
    "PAGE_SIZE": 50,
    "DEFAULT_THROTTLE_CLASSES": [
        "accounts.authentication.AnonRateThrottle",
        "accounts.authentication.OwnerRateThrottle",
    ],
    "DEFAULT_THROTTLE_RATES": {
        "anon": env.str("API_RATE_ANON", default="60/minute"),
        "user": env.str("API_RATE_USER", default="6000/minute"),
        # per robot, on uploads only
        "upload": env.str("API_RATE_UPLOAD", default="1200/minute"),
        # per client address: pairing requests and their polls (no credentials yet)
        "pairing": env.str("API_RATE_PAIRING", default="120/minute"),
        # per client address: Content-Security-Policy violation reports (portal.csp_reports)
        "csp_report": env.str("CSP_REPORT_RATE", default="30/minute"),
    },
    # Proxies in front of the portal; 0 = rate limits per peer address, ignoring a
    # client-supplied X-Forwarded-For. Behind one reverse proxy, 1.
    "NUM_PROXIES": env.int("API_NUM_PROXIES", default=0),
}
SPECTACULAR_SETTINGS = {
    "TITLE": "AuthROS portal API",
    "DESCRIPTION": "For ROS agents and owners: records, grants, integrity-checked content.",
    "VERSION": "1.0.0",
    "SERVE_INCLUDE_SCHEMA": False,
    "COMPONENT_SPLIT_REQUEST": True,
    "ENUM_NAME_OVERRIDES": {
        "RecordStatusEnum": "sharing.models.Record.Status",
        "GrantStatusEnum": "sharing.models.Grant.Status",
        # SM2 ciphertext layout of the key exchange and pairing (accounts.apis)
        "Sm2CiphertextModeEnum": ["C1C3C2"],
    },
    # Swagger UI and Redoc from drf-spectacular-sidecar's static files, not from a CDN:
    # /api/docs/ works offline and loads nothing from another origin.
    "SWAGGER_UI_DIST": "SIDECAR",
    "SWAGGER_UI_FAVICON_HREF": "SIDECAR",
    "REDOC_DIST": "SIDECAR",
}
# Request bodies: the envelope limit plus base64 and JSON overhead.
DATA_UPLOAD_MAX_MEMORY_SIZE = env.int("DATA_UPLOAD_MAX_MEMORY_SIZE", default=12 * 1024 * 1024)

# One JSON object per line (LOG_FORMAT=json, the default: production, the systemd units) or a
# readable line (console: `make run` sets it unless LOG_FORMAT is given); core/logging.py.
LOG_FORMAT = env.str("LOG_FORMAT", default="json")
LOGGING = logging_config(log_format=LOG_FORMAT, level=env.str("LOG_LEVEL", default="INFO"))

# --- Metrics (core/metrics.py, portal/probes.py, docs/operations.md) ---------------------
# GET /metrics is free from this host; from anywhere else it needs `Authorization: Bearer
# <METRICS_TOKEN>` (empty: refused from anywhere else). "Anywhere else" follows API_NUM_PROXIES.
METRICS_TOKEN = env.str("METRICS_TOKEN", default="")
# A host that runs only workers: its worker's main process serves the same /metrics on this
# port (portal/worker_metrics.py; 0: none) and address (the token rule above holds there too).
WORKER_METRICS_PORT = env.int("WORKER_METRICS_PORT", default=0)
WORKER_METRICS_ADDRESS = env.str("WORKER_METRICS_ADDRESS", default="127.0.0.1")

# --- Celery (broker and results in Redis) ------------------------------------------------
# Both in the URL forms of REDIS_URL; a Cluster cannot carry either (kombu has no Cluster
# transport): with REDIS_URL a Cluster, CELERY_BROKER_URL names a plain or Sentinel Redis and the
# results go there too. BROKER_REDIS_URL keeps the broker's URL as written (the admin reads it).
BROKER_REDIS_URL = env.str(
    "CELERY_BROKER_URL", default="" if _REDIS.kind == "cluster" else REDIS_URL
)
if not BROKER_REDIS_URL:
    raise ImproperlyConfigured(
        "REDIS_URL is a Redis Cluster, which cannot be Celery's broker (kombu has no Cluster "
        "transport): set CELERY_BROKER_URL to a plain redis:// or a sentinel:// Redis"
    )
_BROKER = celery_redis(BROKER_REDIS_URL, setting="CELERY_BROKER_URL")
_RESULTS = celery_redis(
    env.str(
        "CELERY_RESULT_BACKEND", default=BROKER_REDIS_URL if _REDIS.kind == "cluster" else REDIS_URL
    ),
    setting="CELERY_RESULT_BACKEND",
)
CELERY_BROKER_URL = _BROKER.url
CELERY_RESULT_BACKEND = _RESULTS.url
CELERY_RESULT_BACKEND_TRANSPORT_OPTIONS = _RESULTS.transport_options
CELERY_RESULT_EXPIRES = 3600
CELERY_TASK_ACKS_LATE = True
CELERY_TASK_REJECT_ON_WORKER_LOST = True
CELERY_WORKER_PREFETCH_MULTIPLIER = 1
# Celery's Django fix-up would close every database connection before and after each task (a
# view's check is one task, and a new connection cost more than the check); it never does by
# count with this, and portal/celery.py closes them as Django's requests do instead.
CELERY_DB_REUSE_MAX = 2**62
CELERY_TASK_SERIALIZER = "json"
CELERY_RESULT_SERIALIZER = "json"
CELERY_ACCEPT_CONTENT = ["json"]
# An unacknowledged message (worker killed) is delivered again after this many seconds.
CELERY_BROKER_TRANSPORT_OPTIONS = {
    "visibility_timeout": env.int("CELERY_VISIBILITY_TIMEOUT", 900),
    **_BROKER.transport_options,  # master_name for Sentinels
}
CELERY_BROKER_CONNECTION_RETRY_ON_STARTUP = True
CELERY_TASK_ALWAYS_EAGER = env.bool("CELERY_TASK_ALWAYS_EAGER", default=False)
CELERY_TASK_DEFAULT_QUEUE = env.str("CELERY_QUEUE", default="authros")
# Integrity checks for views go to "<queue>-verify" (portal/celery.py routes them), so a view
# never waits behind chain work that blocks on receipts. Workers started without -Q consume
# both queues; `make run` adds a worker for the verify queue alone.
CELERY_VERIFY_QUEUE_SUFFIX = "-verify"
CELERY_TASK_QUEUES = (
    Queue(CELERY_TASK_DEFAULT_QUEUE),
    Queue(CELERY_TASK_DEFAULT_QUEUE + CELERY_VERIFY_QUEUE_SUFFIX),
)
CELERY_WORKER_HIJACK_ROOT_LOGGER = False
# Imported by workers once Django's apps are loaded: /metrics on WORKER_METRICS_PORT.
CELERY_IMPORTS = ("portal.worker_metrics",)
# Task events for monitors (Flower, `celery events`: docs/operations.md): what each worker
# received, started, finished or retried, and each task as it is sent. CELERY_TASK_EVENTS=false
# saves their publishes where no monitor runs.
CELERY_WORKER_SEND_TASK_EVENTS = env.bool("CELERY_TASK_EVENTS", default=True)
CELERY_TASK_SEND_SENT_EVENT = CELERY_WORKER_SEND_TASK_EVENTS
_SWEEP_INTERVAL = env.float("ANCHOR_SWEEP_INTERVAL", default=15.0)
# Each app's sweep queues again its chain work pending too long. A sweep still queued when
# the next one is due is worthless: it expires.
# How far back the scan for records missing reads each robot's streams, in seconds.
COMPLETENESS_SCAN_WINDOW = env.float("COMPLETENESS_SCAN_WINDOW", default=86400.0)

CELERY_BEAT_SCHEDULE = {
    "sweep-stale-chain-work": {
        "task": "sharing.tasks.chain_work_sweep",
        "schedule": _SWEEP_INTERVAL,
        "options": {"expires": _SWEEP_INTERVAL},
    },
    "sweep-stale-registrations": {
        "task": "accounts.tasks.chain_work_sweep",
        "schedule": _SWEEP_INTERVAL,
        "options": {"expires": _SWEEP_INTERVAL},
    },
    # Pairing requests nobody answered, a day after they expired (anyone may make them).
    "purge-robot-pairings": {
        "task": "accounts.tasks.robot_pairings_purge",
        "schedule": 3600.0,
        "options": {"expires": 3600.0},
    },
    # Silent robots, low gas, alert deliveries whose message was lost (alerts/).
    "alerts-watch": {
        "task": "alerts.tasks.alerts_watch",
        "schedule": env.float("ALERTS_CHECK_INTERVAL", default=60.0),
        "options": {"expires": env.float("ALERTS_CHECK_INTERVAL", default=60.0)},
    },
    # Deletes records past their robot's retention, and finishes purges
    # (sharing/services/deletion.py).
    "apply-retention": {
        "task": "sharing.tasks.retention_apply",
        "schedule": env.float("RETENTION_INTERVAL", default=3600.0),
        "options": {"expires": env.float("RETENTION_INTERVAL", default=3600.0)},
    },
    # Robots' recent records read for gaps nobody looked at: the owner is alerted of records
    # missing (sharing/services/completeness.py).
    "scan-records-missing": {
        "task": "sharing.tasks.records_missing_scan",
        "schedule": env.float("COMPLETENESS_SCAN_INTERVAL", default=600.0),
        "options": {"expires": env.float("COMPLETENESS_SCAN_INTERVAL", default=600.0)},
    },
    # Compares what the database says is on chain with the chain, and repairs (see below).
    "reconcile-chain": {
        "task": "sharing.tasks.chain_reconcile",
        "schedule": env.float("RECONCILE_INTERVAL", default=60.0),
        "options": {"expires": env.float("RECONCILE_INTERVAL", default=60.0)},
    },
    # Alerts the operator while a disk that uploads are written to runs low (sharing/disk.py).
    "watch-disk-space": {
        "task": "sharing.tasks.disk_space_watch",
        "schedule": env.float("STORAGE_CHECK_INTERVAL", default=60.0),
        "options": {"expires": env.float("STORAGE_CHECK_INTERVAL", default=60.0)},
    },
    # Exports whose message was lost are queued again; expired ones lose their files.
    "sweep-exports": {
        "task": "sharing.tasks.exports_sweep",
        "schedule": 300.0,
        "options": {"expires": 300.0},
    },
}

# --- Anchoring and the ciphertext cache ---------------------------------------------------
# "records": one slot per record (dataUploadBatch, the paper's interface and the benchmarks'
# baseline); "root": one Merkle root per tree of an owner's records (anchorRoot, DESIGN.md).
ANCHOR_MODE = env.str("ANCHOR_MODE", default="root")
if ANCHOR_MODE not in ("records", "root"):
    raise ImproperlyConfigured(f"ANCHOR_MODE must be records or root, not {ANCHOR_MODE!r}")
# Records per dataUploadBatch transaction (records mode; the contract takes at most 256).
ANCHOR_BATCH_MAX = env.int("ANCHOR_BATCH_MAX", default=100)
# Records per Merkle tree (root mode): a root costs the same gas whatever its size.
ANCHOR_ROOT_MAX = env.int("ANCHOR_ROOT_MAX", default=4096)
# Seconds a new record may wait for others of its owner to fill a batch.
ANCHOR_MAX_WAIT = env.float("ANCHOR_MAX_WAIT", default=1.0)
# Seconds without a new record of the owner that close its batch before ANCHOR_MAX_WAIT (the
# uploads paused: a robot's batch or a burst is complete); 0 waits ANCHOR_MAX_WAIT always.
ANCHOR_QUIET = env.float("ANCHOR_QUIET", default=0.1)
if ANCHOR_QUIET < 0 or ANCHOR_MAX_WAIT < 0:
    raise ImproperlyConfigured("ANCHOR_MAX_WAIT and ANCHOR_QUIET must not be negative")
# Pending work older than this is queued again by the sweep (lost message, dead worker).
ANCHOR_STALE_AFTER = env.float("ANCHOR_STALE_AFTER", default=60.0)
ANCHOR_MAX_ATTEMPTS = env.int("ANCHOR_MAX_ATTEMPTS", default=20)
# --- Reconciliation and chain resets (sharing/services/reconcile.py) ---
# Seconds between runs of the job comparing the database with the chain (beat schedule above).
RECONCILE_INTERVAL = env.float("RECONCILE_INTERVAL", default=60.0)
# Rows (records, owners, grants) each run reads from the chain besides the recent records: all
# of them are looked at within (rows / RECONCILE_CHUNK) runs.
RECONCILE_CHUNK = env.int("RECONCILE_CHUNK", default=500)
# Seconds every process reuses the verdict "is the node still the chain we deployed on".
CHAIN_IDENTITY_CACHE_SECONDS = env.float("CHAIN_IDENTITY_CACHE_SECONDS", default=10.0)
# Seconds between the blocks the node makes even with nothing to mine (a proof-of-authority
# network's block period, anvil --block-time); 0: blocks only when transactions arrive (anvil's
# automine, `make run`'s default). See chainworker.services.chain_stalled.
CHAIN_BLOCK_TIME = env.float("CHAIN_BLOCK_TIME", default=0.0)
# No new block for this long (while work waits, or ever if CHAIN_BLOCK_TIME is set) is a stall:
# sending pauses, using up no attempt, and an operator alert is raised. Keep it below
# CHAIN_RECEIPT_TIMEOUT, so a receipt timeout on a stalled chain costs no attempt either.
CHAIN_STALL_AFTER = env.float(
    "CHAIN_STALL_AFTER", default=10 * CHAIN_BLOCK_TIME if CHAIN_BLOCK_TIME > 0 else 60.0
)
# Batch transactions one owner may have in flight at once (consecutive nonces).
ANCHOR_INFLIGHT = env.int("ANCHOR_INFLIGHT", default=4)
# Seconds an anchoring lock outlives a worker that died holding it (renewed while alive).
ANCHOR_LOCK_TTL = env.float("ANCHOR_LOCK_TTL", default=30.0)
ENVELOPE_CACHE_TTL = env.int("ENVELOPE_CACHE_TTL", default=3600)
ENVELOPE_CACHE_MAX_ITEM_BYTES = env.int("ENVELOPE_CACHE_MAX_ITEM_BYTES", default=2 * 1024 * 1024)
# All cached envelopes together; the oldest go first past it (sharing/cache.py).
ENVELOPE_CACHE_MAX_BYTES = env.int("ENVELOPE_CACHE_MAX_BYTES", default=256 * 1024 * 1024)
ENVELOPE_MAX_BYTES = env.int("ENVELOPE_MAX_BYTES", default=8 * 1024 * 1024)
# Retention and deletion (sharing/services/deletion.py): records per batch, batches per run
# (the next run goes on), and seconds a run's lock outlives a worker that died holding it.
RETENTION_BATCH = env.int("RETENTION_BATCH", default=500)
RETENTION_MAX_BATCHES = env.int("RETENTION_MAX_BATCHES", default=20)
RETENTION_LOCK_TTL = env.float("RETENTION_LOCK_TTL", default=900.0)
# How long a web request waits for the worker's integrity verdict.
VERIFY_TIMEOUT = env.float("VERIFY_TIMEOUT", default=30.0)
# A single record's check asked of a verify worker through Redis, not as a Celery task
# (sharing/verification/direct.py); off, every check is a task (as before, and for comparison).
VERIFY_DIRECT = env.bool("VERIFY_DIRECT", default=True)
# Series (sharing/series.py, docs/api.md): the longest capture-time range one series covers,
# and the most records it may check (every record in range is checked, none skipped).
SERIES_MAX_RANGE = timedelta(seconds=env.int("SERIES_MAX_RANGE_SECONDS", default=6 * 3600))
SERIES_MAX_RECORDS = env.int("SERIES_MAX_RECORDS", default=216_000)
# Exports (sharing/exports/, docs/export.md): records in one export at most, records checked
# against the chain per run of the integrity check, and hours its files are kept.
EXPORT_MAX_RECORDS = env.int("EXPORT_MAX_RECORDS", default=2_000_000)
EXPORT_BATCH = env.int("EXPORT_BATCH", default=200)
EXPORT_TTL_HOURS = env.int("EXPORT_TTL_HOURS", default=24)
EXPORT_REQUEUE_AFTER = env.int("EXPORT_REQUEUE_AFTER", default=600)

# --- Alerts (alerts/, docs/alerts.md) -----------------------------------------------------
# E-mail goes through Django's mail framework: SMTP when EMAIL_HOST is set, else printed on the
# console (`make run`); EMAIL_BACKEND overrides both.
EMAIL_HOST = env.str("EMAIL_HOST", default="")
EMAIL_PORT = env.int("EMAIL_PORT", default=25)
EMAIL_HOST_USER = env.str("EMAIL_HOST_USER", default="")
EMAIL_HOST_PASSWORD = env.str("EMAIL_HOST_PASSWORD", default="")
EMAIL_USE_TLS = env.bool("EMAIL_USE_TLS", default=False)
EMAIL_USE_SSL = env.bool("EMAIL_USE_SSL", default=False)
EMAIL_TIMEOUT = env.float("EMAIL_TIMEOUT", default=10.0)
EMAIL_BACKEND = env.str(
    "EMAIL_BACKEND",
    default="django.core.mail.backends.smtp.EmailBackend"
    if EMAIL_HOST
    else "django.core.mail.backends.console.EmailBackend",
)
DEFAULT_FROM_EMAIL = env.str("DEFAULT_FROM_EMAIL", default="AuthROS portal <alerts@localhost>")
# The portal's public address, for the link in alert e-mails (empty: no link).
ALERTS_PORTAL_URL = env.str("ALERTS_PORTAL_URL", default="")
# Seconds to connect to a webhook receiver, and again to read its answer.
ALERTS_WEBHOOK_TIMEOUT = env.float("ALERTS_WEBHOOK_TIMEOUT", default=5.0)
# Webhooks to loopback, private, link-local or reserved addresses are refused unless this is
# set (a receiver on the portal's own network; the tests).
ALERTS_WEBHOOK_ALLOW_PRIVATE = env.bool("ALERTS_WEBHOOK_ALLOW_PRIVATE", default=False)
# Webhooks go to ports 80 and 443; the operator may allow more (comma-separated numbers).
ALERTS_WEBHOOK_PORTS = [int(port) for port in env.list("ALERTS_WEBHOOK_PORTS", default=[])]
ALERTS_WEBHOOKS_PER_OWNER = env.int("ALERTS_WEBHOOKS_PER_OWNER", default=5)
# A failed delivery is tried again after 2, 4, 8 ... seconds (at most ALERTS_RETRY_BACKOFF_MAX
# apart), this many times, then marked failed in the owner's delivery log.
ALERTS_DELIVERY_MAX_RETRIES = env.int("ALERTS_DELIVERY_MAX_RETRIES", default=8)
ALERTS_RETRY_BACKOFF_MAX = env.int("ALERTS_RETRY_BACKOFF_MAX", default=600)
# A delivery still pending this long after its last attempt is queued again by the watch.
ALERTS_DELIVERY_STALE_AFTER = env.float("ALERTS_DELIVERY_STALE_AFTER", default=1800.0)

STORAGES = {
    "default": {"BACKEND": "django.core.files.storage.FileSystemStorage"},
    "staticfiles": {"BACKEND": "django.contrib.staticfiles.storage.StaticFilesStorage"},
    # The durable copy of every envelope: the local disk, or an S3 bucket (core/storage_url.py).
    "envelopes": envelope_storage_config(
        env.str("ENVELOPE_STORAGE_URL", default=""),
        media_root=MEDIA_ROOT,
        endpoint_url=env.str("ENVELOPE_S3_ENDPOINT_URL", default=""),
        region=env.str("ENVELOPE_S3_REGION", default=""),
    ),
}
# Disks this host writes uploads to (the local envelope storage, SQLite; sharing/disk.py): an
# upload that would leave less than STORAGE_MIN_FREE_BYTES free is refused (503, the robot
# spools it; 0 never refuses), and the operator is alerted below STORAGE_LOW_FREE_BYTES.
STORAGE_MIN_FREE_BYTES = env.int("STORAGE_MIN_FREE_BYTES", default=128 * 1024**2)
STORAGE_LOW_FREE_BYTES = env.int("STORAGE_LOW_FREE_BYTES", default=2 * 1024**3)
