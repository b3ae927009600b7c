"""Loaded by pytest before Django's settings (`-p tests.support.environment` in pyproject.toml).

The suite uses a Redis database of its own (TEST_REDIS_URL, default db 14), so that tests
which flush Redis never touch a developer's data, and a Celery queue of its own per test run,
so that the workers of two runs on one machine never take each other's messages.
"""

import os

os.environ["REDIS_URL"] = os.environ.get("TEST_REDIS_URL", "redis://127.0.0.1:6379/14")
# Every test closes its connections, so that PostgreSQL can drop the test database.
os.environ.setdefault("DATABASE_CONN_MAX_AGE", "0")
os.environ["CELERY_QUEUE"] = f"authros-test-{os.getpid()}"
os.environ.pop("CELERY_BROKER_URL", None)
os.environ.pop("CELERY_RESULT_BACKEND", None)
# CI machines may have little disk left (a few hundred MB seen): uploads are refused only on
# the last 16 MiB here; tests/sharing/test_disk_space.py sets the floor around the real room.
os.environ.setdefault("STORAGE_MIN_FREE_BYTES", str(16 * 1024**2))
