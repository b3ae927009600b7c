"""The whole stack, as `make run` starts it: `python -m stack run`.

Redis (reused if one answers at REDIS_URL), anvil with its state file (reused if a node
answers at CHAIN_RPC_URL), `manage.py migrate` and `chain_deploy`, a Celery worker for chain
work, one for the verify queue alone, beat, the portal under gunicorn, and on the ROS side a
roscore (reused if one answers), the simulated robot and an agent for a demo owner (with
--ros2 / STACK_ROS2=true: no roscore, the simulated ROS 2 robot and the agent in ROS 2 mode,
over Cyclone DDS on loopback, <workdir>/cyclonedds.xml, domain ROS_DOMAIN_ID). It prints
where to click, then waits; SIGINT or SIGTERM stops everything it started, in order, and so
does any of its processes exiting. Once everything answers it writes <workdir>/stack.json
(URLs, the environment its processes got, their pids) for programs that drive it: the
benchmarks and the test of `make run`. Django steps run as `manage.py` subprocesses, so this
module never imports the portal's apps.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from types import FrameType
from typing import Any, TextIO
from urllib.parse import urlsplit

from stack.anvil import AnvilError, AnvilProcess, free_port, rpc_answers, start_anvil
from stack.processes import (
    PYTHON,
    REPO_ROOT,
    WEB_MAX_THREADS,
    Children,
    StackError,
    WebSizing,
    celery_beat,
    celery_worker,
    http_answers,
    log_tail,
    logs_rotate,
    manage,
    redis_answers,
    redis_start,
    redis_stop,
    ros_master_answers,
    wait_until,
    web_server,
    web_sizing,
)

BANNER = "AuthROS portal is up."
STATE_FILE = "stack.json"
WEB_START_TIMEOUT = 90.0
ROS_START_TIMEOUT = 30.0
# Seconds between looks at the logs' sizes (StackConfig.log_max_bytes).
LOG_ROTATE_INTERVAL = 30.0
# Seconds the demo robot's pairing may take (it is approved at once).
PAIR_TIMEOUT = 60
# Seconds between writes of the chain state (stack/anvil.py StateKeeper): a crash of anvil
# loses at most the last second, about the last block.
ANVIL_STATE_INTERVAL = 1.0
# The development node keeps the transactions, receipts and logs of this many latest blocks
# (about three weeks of make run's traffic, a few KiB a block in its state file): an export's
# verifier reads the receipt of every anchoring transaction in it, so a node that had dropped
# them (1,024 blocks, half an hour of the demo robot, until 2026-12) failed every export made
# more than half an hour before.
ANVIL_TRANSACTION_BLOCKS = 1_000_000
# The processes that count for /metrics (core/metrics.py), each in its own folder.
METRICS_SERVICES = ("web", "worker", "verify")
# Stopped one at a time in this order (anvil and Redis after them): nothing new is
# scheduled while workers finish, and the chain outlives everything that writes to it.
STOP_ORDER = (("beat",), ("web",), ("worker", "verify"), ("agent",), ("sim",), ("roscore",))
_STOP = {  # signal and seconds each process gets before its group is killed
    "beat": (signal.SIGTERM, 10.0),
    "web": (signal.SIGTERM, 15.0),
    "worker": (signal.SIGTERM, 30.0),
    "verify": (signal.SIGTERM, 30.0),
    "agent": (signal.SIGINT, 20.0),
    "sim": (signal.SIGINT, 10.0),
    "roscore": (signal.SIGINT, 15.0),
}


def is_loopback(host: str) -> bool:
    """Whether a listening address is this machine's alone (127.0.0.0/8, ::1, localhost)."""
    return host == "localhost" or host.startswith("127.") or host in ("::1", "[::1]")


def _env_bool(environ: dict[str, str], name: str, default: bool) -> bool:
    value = environ.get(name, "").strip().lower()
    return default if not value else value in ("1", "true", "yes", "on")


@dataclass(frozen=True)
class StackConfig:
    """What to start and where. Every field has an environment variable (from_environment)."""

    workdir: Path  # AUTHROS_VAR_DIR: database, secrets, logs, anvil state, demo files
    host: str = "127.0.0.1"  # PORTAL_HOST; 0.0.0.0 (or ::) listens on every address
    # PORTAL_PUBLIC_URL: where robots and browsers on the network reach the portal (its host is
    # allowed, beside loopback); needed when PORTAL_HOST is not a loopback address
    public_url: str = ""
    port: int = 8000  # PORTAL_PORT; 0 = a free port
    anvil_port: int = 8545  # ANVIL_PORT; 0 = a free port
    chain_rpc_url: str = ""  # CHAIN_RPC_URL; "" = http://127.0.0.1:<anvil_port>
    block_time: float | None = None  # ANVIL_BLOCK_TIME; None = a block per transaction
    redis_url: str = "redis://127.0.0.1:6379/0"  # REDIS_URL
    database_url: str = ""  # DATABASE_URL; "" = SQLite in workdir
    queue: str = "authros"  # CELERY_QUEUE; the verify queue is <queue>-verify
    workers: int = 2  # STACK_WORKERS: pool processes of the chain worker
    verify_workers: int = 1  # STACK_VERIFY_WORKERS: pool processes of the verify worker
    web_workers: int = 0  # WEB_WORKERS; 0 = sized to the machine
    web_threads: int = 0  # WEB_THREADS; 0 = sized to the machine
    web: bool = True  # STACK_WEB: serve the portal
    ros: bool = True  # STACK_ROS: roscore, the simulated robot and the demo agent
    ros_master_uri: str = "http://127.0.0.1:11311"  # ROS_MASTER_URI
    ros2: bool = False  # STACK_ROS2: the robot on ROS 2 (Cyclone DDS, loopback), no roscore
    ros_domain_id: int = 0  # ROS_DOMAIN_ID: the DDS domain of the ROS 2 robot
    debug: bool = False  # DJANGO_DEBUG
    log_max_bytes: int = 32 * 1024**2  # STACK_LOG_MAX_BYTES: a log past it is rotated; 0 = never
    log_keep: int = 3  # STACK_LOG_KEEP: rotated copies kept of each log (NAME.log.1 ...)

    @classmethod
    def from_environment(cls, environ: dict[str, str] | None = None) -> StackConfig:
        environ = dict(os.environ if environ is None else environ)
        block_time = environ.get("ANVIL_BLOCK_TIME", "")
        return cls(
            workdir=Path(environ.get("AUTHROS_VAR_DIR") or REPO_ROOT / "var"),
            host=environ.get("PORTAL_HOST", "127.0.0.1"),
            public_url=environ.get("PORTAL_PUBLIC_URL", "").rstrip("/"),
            port=int(environ.get("PORTAL_PORT", "8000")),
            anvil_port=int(environ.get("ANVIL_PORT", "8545")),
            chain_rpc_url=environ.get("CHAIN_RPC_URL", ""),
            block_time=float(block_time) if block_time else None,
            redis_url=environ.get("REDIS_URL", "redis://127.0.0.1:6379/0"),
            database_url=environ.get("DATABASE_URL", ""),
            queue=environ.get("CELERY_QUEUE", "authros"),
            workers=int(environ.get("STACK_WORKERS", "2")),
            verify_workers=int(environ.get("STACK_VERIFY_WORKERS", "1")),
            web_workers=int(environ.get("WEB_WORKERS", "0")),
            web_threads=int(environ.get("WEB_THREADS", "0")),
            web=_env_bool(environ, "STACK_WEB", True),
            ros=_env_bool(environ, "STACK_ROS", True),
            ros_master_uri=environ.get("ROS_MASTER_URI", "http://127.0.0.1:11311"),
            ros2=_env_bool(environ, "STACK_ROS2", False),
            ros_domain_id=int(environ.get("ROS_DOMAIN_ID") or "0"),
            debug=_env_bool(environ, "DJANGO_DEBUG", False),
            log_max_bytes=int(environ.get("STACK_LOG_MAX_BYTES") or 32 * 1024**2),
            log_keep=max(int(environ.get("STACK_LOG_KEEP") or "3"), 1),
        )

    def resolved(self) -> StackConfig:
        """Free ports picked, default URLs filled in, the work folder absolute."""
        workdir = self.workdir.resolve()
        anvil_port = self.anvil_port or free_port()
        return replace(
            self,
            workdir=workdir,
            port=self.port or free_port(),
            anvil_port=anvil_port,
            chain_rpc_url=self.chain_rpc_url or f"http://127.0.0.1:{anvil_port}",
            database_url=self.database_url or f"sqlite:///{workdir / 'db.sqlite3'}",
            # ros needs the portal: the agent uploads to it
            ros=self.ros and self.web,
        )

    def sizing(self) -> WebSizing:
        machine = web_sizing()
        return WebSizing(
            workers=self.web_workers or machine.workers,
            threads=self.web_threads or machine.threads,
        )


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived."""


class Stack:
    """The processes `make run` starts; start(), then wait(), then stop() (always)."""

    def __init__(self, config: StackConfig, *, out: TextIO | None = None) -> None:
        self.config = config.resolved()
        self.out = out or sys.stdout
        self.workdir = self.config.workdir
        self.logs = self.workdir / "log"
        self.metrics_dir = self.workdir / "metrics"
        self.children = Children(self.logs, die_with_parent=True)
        self.anvil: AnvilProcess | None = None
        self.redis_started = False
        self.demo: dict[str, Any] | None = None
        self._web_command: list[str] = []

    # --- what the processes see ----------------------------------------------------------

    @property
    def web_url(self) -> str:
        host = "127.0.0.1" if self.config.host in ("0.0.0.0", "") else self.config.host  # noqa: S104
        return f"http://{host}:{self.config.port}"

    @property
    def public_url(self) -> str:
        """Where robots and browsers reach the portal: PORTAL_PUBLIC_URL, else web_url."""
        return self.config.public_url or self.web_url

    @property
    def allowed_hosts(self) -> list[str]:
        """The Host headers the portal answers: DJANGO_ALLOWED_HOSTS if set, else loopback's,
        the address it listens on and the public URL's host."""
        if os.environ.get("DJANGO_ALLOWED_HOSTS"):
            return os.environ["DJANGO_ALLOWED_HOSTS"].split(",")
        hosts = ["localhost", "127.0.0.1", "[::1]"]
        for host in (self.config.host, urlsplit(self.public_url).hostname or ""):
            host = f"[{host}]" if ":" in host else host
            if host not in (*hosts, "", "0.0.0.0", "[::]"):  # noqa: S104
                hosts.append(host)
        return hosts

    def environment(self) -> dict[str, str]:
        """The settings every process of the stack gets (on top of this process's own)."""
        config = self.config
        env = {
            "DJANGO_ALLOWED_HOSTS": ",".join(self.allowed_hosts),
            "DJANGO_SETTINGS_MODULE": "portal.settings",
            "AUTHROS_VAR_DIR": str(self.workdir),
            "DATABASE_URL": config.database_url,
            "REDIS_URL": config.redis_url,
            "CELERY_QUEUE": config.queue,
            "CHAIN_RPC_URL": config.chain_rpc_url,
            "DJANGO_DEBUG": "true" if config.debug else "false",
            # Readable lines in the terminal's logs; LOG_FORMAT=json for what production writes.
            "LOG_FORMAT": os.environ.get("LOG_FORMAT") or "console",
        }
        if config.ros and config.ros2:
            env |= {
                "CYCLONEDDS_URI": (self.workdir / "cyclonedds.xml").as_uri(),
                "ROS_DOMAIN_ID": str(config.ros_domain_id),
                "ROS_HOME": str(self.workdir / "ros"),
            }
        elif config.ros:
            env |= {
                "ROS_MASTER_URI": config.ros_master_uri,
                "ROS_IP": os.environ.get("ROS_IP", "127.0.0.1"),
                "ROS_HOME": str(self.workdir / "ros"),
                "ROS_LOG_DIR": str(self.logs / "ros"),
            }
        return env

    def _child_env(self) -> dict[str, str]:
        env = {**os.environ, **self.environment(), "PYTHONUNBUFFERED": "1"}
        for name in ("ROS_HOSTNAME", "ROS_NAMESPACE"):  # ROS_IP says where we are
            env.pop(name, None)
        return env

    # --- start ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start everything; StackError (or AnvilError) if a part does not come up."""
        config = self.config
        for folder in (self.logs, self.workdir / "anvil"):
            folder.mkdir(parents=True, exist_ok=True)
        # What the last run counted goes, the folders of services no longer run too.
        shutil.rmtree(self.metrics_dir, ignore_errors=True)
        self._start_redis()
        self._start_chain()
        self._manage("migrate", "--noinput")
        self._say_output(self._manage("chain_deploy"))
        self._say_output(self._manage("chain_status"))
        self._say(f"starting the Celery workers and beat (logs in {self._shown(self.logs)}/)")
        self._spawn("worker", celery_worker("authros-worker", concurrency=config.workers))
        # Views' integrity checks have a worker of their own: they never wait behind receipts.
        verify_queue = f"{config.queue}-verify"
        self._spawn(
            "verify",
            celery_worker(
                "authros-verify", concurrency=config.verify_workers, queues=[verify_queue]
            ),
        )
        self._spawn("beat", celery_beat(self.workdir / "celerybeat-schedule"))
        if config.web:
            self._start_web()
        if config.ros:
            self._start_ros()
        self._write_state()

    def _start_redis(self) -> None:
        url = self.config.redis_url
        if redis_answers(url):
            self._say(f"reusing the Redis at {url}")
            return
        redis_start(url, self.workdir / "redis")
        self.redis_started = True
        self._say(f"started Redis at {url} (stopped again with the stack)")

    def _start_chain(self) -> None:
        config = self.config
        if rpc_answers(config.chain_rpc_url):
            self._say(f"reusing the chain node at {config.chain_rpc_url}")
            return
        if urlsplit(config.chain_rpc_url).port != config.anvil_port:
            raise StackError(f"no chain node answers at {config.chain_rpc_url}")
        state = self.workdir / "anvil" / "state.json"
        self._say(
            f"starting anvil on 127.0.0.1:{config.anvil_port} (state kept in {self._shown(state)})"
        )
        self.anvil = start_anvil(
            block_time=config.block_time,
            state_path=state,
            port=config.anvil_port,
            state_interval=ANVIL_STATE_INTERVAL,
            transaction_blocks=ANVIL_TRANSACTION_BLOCKS,
            log_path=self.logs / "anvil.log",
            die_with_parent=True,
            zero_gas=True,
        )

    def _start_web(self) -> None:
        config = self.config
        sizing = config.sizing()
        self._say(
            f"starting the portal on {self._listening()} (gunicorn, {sizing.workers} workers x "
            f"{sizing.threads} threads, DEBUG {'on' if config.debug else 'off'})"
        )
        self._web_command = web_server(config.host, config.port, sizing)
        self._spawn("web", self._web_command)
        wait_until(
            lambda: http_answers(f"{self.web_url}/admin/login/"),
            timeout=WEB_START_TIMEOUT,
            what=f"the portal on {self.web_url} (see {self.logs}/web.log)",
            alive=self.children.check_alive,
        )

    def _start_ros(self) -> None:
        config = self.config
        (self.logs / "ros").mkdir(parents=True, exist_ok=True)
        (self.workdir / "ros").mkdir(parents=True, exist_ok=True)
        if config.ros2:
            self._start_ros2()
            return
        uri = config.ros_master_uri
        if ros_master_answers(uri):
            self._say(f"reusing the ROS master at {uri}")
        else:
            port = urlsplit(uri).port or 11311
            self._say(f"starting roscore on port {port}")
            self._spawn("roscore", ["roscore", "-p", str(port)])
            wait_until(
                lambda: ros_master_answers(uri),
                timeout=ROS_START_TIMEOUT,
                what=f"roscore (see {self.logs}/roscore.log)",
                alive=self.children.check_alive,
                interval=0.3,
            )
        demo_dir = self.workdir / "demo"
        self.demo = json.loads(
            self._manage("demo_setup", "--dir", str(demo_dir), "--portal-url", self.web_url)
        )
        if not self.demo["robot_paired"]:
            self._pair_demo_robot(Path(self.demo["robot_dir"]))
        self._say("starting the simulated robot and the demo owner's agent")
        self._spawn("sim", [PYTHON, "-m", "ros_agent.sim"])
        self._spawn("agent", [PYTHON, "-m", "ros_agent", "--config", self.demo["agent_config"]])

    def _pair_demo_robot(self, folder: Path) -> None:
        """Pair the demo robot as any robot is paired: `python -m ros_agent pair` makes its SM2
        key pair and asks the portal; with no human here to type the code on the robots page,
        `manage.py robot_pair_approve` answers for the demo owner through the same service; the
        robot then receives its token and the owner's key encrypted to its SM2 key."""
        self._say(f"pairing the demo robot (python -m ros_agent pair --dir {self._shown(folder)})")
        log = (self.logs / "pair.log").open("ab")
        robot = subprocess.Popen(
            [PYTHON, "-m", "ros_agent", "pair", "--portal", self.web_url, "--name", "demo-robot",
             "--dir", str(folder), "--json", "--timeout", str(PAIR_TIMEOUT)],
            cwd=REPO_ROOT,
            env=self._child_env(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
        )  # fmt: skip
        try:
            requested = json.loads(robot.stdout.readline() or "{}")
            if requested.get("event") != "requested":
                raise StackError(f"the demo robot could not ask to be paired (see {log.name})")
            self._manage(
                "robot_pair_approve", "--owner", self.demo["username"], "--code", requested["code"]
            )
            robot.communicate(timeout=PAIR_TIMEOUT)
        except subprocess.TimeoutExpired:
            robot.kill()
            robot.wait()
            raise StackError(f"the demo robot was not paired in time (see {log.name})") from None
        finally:
            if robot.poll() is None:
                robot.kill()
                robot.wait()
            log.close()
        if robot.returncode != 0:
            raise StackError(f"pairing the demo robot failed (see {log.name})")

    def _start_ros2(self) -> None:
        """The simulated ROS 2 robot and the agent in ROS 2 mode, over Cyclone DDS on loopback."""
        from ros_agent.dds import write_loopback_config

        write_loopback_config(self.workdir / "cyclonedds.xml")
        demo_dir = self.workdir / "demo"
        self.demo = json.loads(
            self._manage("demo_setup", "--dir", str(demo_dir), "--portal-url", self.web_url)
        )
        self._say(
            f"starting the simulated ROS 2 robot and the demo owner's agent "
            f"(Cyclone DDS on loopback, domain {self.config.ros_domain_id})"
        )
        self._spawn("sim", [PYTHON, "-m", "ros_agent.sim2"])
        self._spawn(
            "agent", [PYTHON, "-m", "ros_agent", "--ros2", "--config", str(demo_dir / "agent.yaml")]
        )

    def _spawn(self, name: str, argv: list[str]) -> None:
        stop_signal, stop_timeout = _STOP[name]
        env = self._child_env()
        if name in METRICS_SERVICES:
            # Each service counts in a folder of its own, which it empties as it starts; the
            # web's /metrics adds up every folder of the host (core/metrics.py).
            env["PROMETHEUS_MULTIPROC_DIR"] = str(self.metrics_dir / name)
        self.children.spawn(name, argv, env=env, stop_signal=stop_signal, stop_timeout=stop_timeout)

    def _manage(self, *args: str) -> str:
        """A `manage.py` step; its stdout (output in log/manage.log), StackError if it fails."""
        done = subprocess.run(
            manage(*args),
            cwd=REPO_ROOT,
            env=self._child_env(),
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            check=False,
        )
        with (self.logs / "manage.log").open("a") as log:
            log.write(f"$ manage.py {' '.join(args)}\n{done.stdout}{done.stderr}")
        if done.returncode != 0:
            output = (done.stdout + done.stderr).strip()
            raise StackError(f"manage.py {args[0]} failed ({done.returncode}):\n{output[-3000:]}")
        return done.stdout

    # --- running -------------------------------------------------------------------------

    def _listening(self) -> str:
        """Where the portal listens, as the start line says it: its URL on loopback, else the
        address and port with where robots reach it (so 0.0.0.0 is not mistaken for loopback)."""
        if is_loopback(self.config.host):
            return f"{self.web_url}/"
        return f"{self.config.host}:{self.config.port}, reached at {self.public_url}/"

    def banner(self) -> str:
        # Robots and browsers on the network reach every page at the public URL, not loopback.
        url = self.public_url
        lines = ["", f"  {BANNER}"]
        if self.config.web:
            lines.append(f"    Portal:        {self.public_url}/")
            lines.append(f"    Allowed hosts: {', '.join(self.allowed_hosts)}")
            lines.append(
                f"    Pair a robot:  authros-agent pair --portal {self.public_url} --name NAME"
            )
            if is_loopback(self.config.host):
                lines.append(
                    "                   (this machine only; for robots on the network: "
                    "PORTAL_HOST=0.0.0.0 PORTAL_PUBLIC_URL=http://ADDRESS:PORT make run)"
                )
        if self.demo is not None:
            password = (Path(self.demo["password_file"])).read_text().strip()
            lines.append(
                f"    Log in as:     {self.demo['username']} / {password}   "
                "(the simulated robot's data arrives there)"
            )
        if self.config.web:
            lines += [
                f"    Admin console: {url}/admin/   "
                "(create a login: .venv/bin/python manage.py createsuperuser)",
                f"    API docs:      {url}/api/docs/",
            ]
        lines += [
            f"    Chain node:    {self.config.chain_rpc_url}",
            f"    Logs:          {self._shown(self.logs)}/",
            "  Press Ctrl-C to stop everything started here.",
            "",
        ]
        return "\n".join(lines)

    def wait(self) -> int:
        """Until a process exits (then 1) or a signal interrupts (Interrupted); meanwhile the
        logs are rotated (a service that runs for weeks must not fill its disk with them)."""
        rotate_at = time.monotonic() + LOG_ROTATE_INTERVAL
        while True:
            if self.config.log_max_bytes > 0 and time.monotonic() >= rotate_at:
                rotate_at = time.monotonic() + LOG_ROTATE_INTERVAL
                logs_rotate(
                    self.logs, max_bytes=self.config.log_max_bytes, keep=self.config.log_keep
                )
            if (child := self.children.exited()) is not None:
                self._say(
                    f"{child.name} exited with {child.process.returncode}; "
                    f"stopping the rest. The end of {self._shown(child.log)}:\n"
                    f"{log_tail(child.log, 15)}"
                )
                return 1
            if self.anvil is not None and self.anvil.process.poll() is not None:
                self._say(f"anvil exited; stopping the rest (see {self.logs}/anvil.log)")
                return 1
            time.sleep(0.5)

    def state(self) -> dict[str, Any]:
        """What stack.json holds."""
        processes = self.children.pids()
        if self.anvil is not None:
            processes["anvil"] = self.anvil.process.pid
        return {
            "pid": os.getpid(),
            "config": json.loads(json.dumps(asdict(self.config), default=str)),
            "web_url": self.web_url if self.config.web else None,
            "web_command": self._web_command,
            "chain_rpc_url": self.config.chain_rpc_url,
            "env": self.environment(),
            "logs": str(self.logs),
            "processes": processes,
            "redis_started": self.redis_started,
            "demo": self.demo,
        }

    def _write_state(self) -> None:
        path = self.workdir / STATE_FILE
        partial = path.with_suffix(".tmp")
        partial.write_text(json.dumps(self.state(), indent=2) + "\n")
        partial.replace(path)  # whoever waits for it never reads half of it

    # --- stop ----------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop everything this stack started, in STOP_ORDER, then anvil, then Redis."""
        (self.workdir / STATE_FILE).unlink(missing_ok=True)
        started = [name for name in self.children.names() if self.children[name].running()]
        if started or self.anvil is not None or self.redis_started:
            self._say("stopping what the stack started")
        for names in STOP_ORDER:
            self.children.stop_many(names)
        self.children.stop_all()
        if self.anvil is not None:
            self.anvil.stop()  # SIGTERM: it writes its state file first
            self.anvil = None
        if self.redis_started:
            self._say("stopping the redis-server started by the stack")
            redis_stop(self.config.redis_url)
            self.redis_started = False

    # --- output --------------------------------------------------------------------------

    def _say(self, message: str) -> None:
        tag = "\033[1;32m[stack]\033[0m" if self.out.isatty() else "[stack]"
        self.out.write(f"{tag} {message}\n")
        self.out.flush()

    def _say_output(self, text: str) -> None:
        if text.strip():
            self.out.write(text if text.endswith("\n") else text + "\n")
            self.out.flush()

    def _shown(self, path: Path) -> str:
        """path relative to the repository when it is inside it (var/log), else absolute."""
        try:
            return str(path.relative_to(REPO_ROOT))
        except ValueError:
            return str(path)


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise Interrupted(signal.Signals(signum).name)


def run(config: StackConfig) -> int:
    """Start the stack, print the banner, wait; stop it on a signal or when a process exits."""
    stack = Stack(config)
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    code = 1
    try:
        stack.start()
        print(stack.banner(), flush=True)
        code = stack.wait()
    except Interrupted:
        code = 0
    except (StackError, AnvilError) as exc:
        print(f"make run: {exc}", file=sys.stderr, flush=True)
    finally:
        # A second Ctrl-C must not cut the stop short: it would leave processes behind.
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)
        stack.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return code


def redis(url: str, folder: Path) -> int:
    """Make sure a Redis answers at url: reuse it, else start one (left running)."""
    if redis_answers(url):
        return 0
    print(f"starting redis-server for {url}", file=sys.stderr)
    try:
        redis_start(url, folder)
    except (StackError, subprocess.CalledProcessError) as exc:
        print(exc, file=sys.stderr)
        return 1
    return 0


def main(argv: list[str]) -> int:
    """`python -m stack run [options]` or `python -m stack redis`."""
    defaults = StackConfig.from_environment()
    parser = argparse.ArgumentParser(prog="python -m stack", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("redis", help="make sure a Redis answers at REDIS_URL (start one)")
    run_parser = commands.add_parser("run", help="start the whole stack (what `make run` does)")
    options = (
        ("--workdir", Path, defaults.workdir, "AUTHROS_VAR_DIR: database, secrets, logs, state"),
        ("--host", str, defaults.host, "PORTAL_HOST (0.0.0.0: every address)"),
        ("--public-url", str, defaults.public_url, "PORTAL_PUBLIC_URL: robots reach it there"),
        ("--port", int, defaults.port, "PORTAL_PORT (0 = a free port)"),
        ("--anvil-port", int, defaults.anvil_port, "ANVIL_PORT (0 = a free port)"),
        ("--block-time", float, defaults.block_time, "ANVIL_BLOCK_TIME, seconds"),
        ("--queue", str, defaults.queue, "CELERY_QUEUE (verify queue: QUEUE-verify)"),
        ("--workers", int, defaults.workers, "STACK_WORKERS: chain worker processes"),
        ("--verify-workers", int, defaults.verify_workers, "STACK_VERIFY_WORKERS"),
        ("--web-workers", int, defaults.web_workers, "WEB_WORKERS (0 = cores + 1)"),
        (
            "--web-threads",
            int,
            defaults.web_threads,
            f"WEB_THREADS per web worker (0 = {WEB_MAX_THREADS})",
        ),
    )
    for flag, kind, default, what in options:
        run_parser.add_argument(flag, type=kind, default=default, help=f"{what} [{default}]")
    for flag, default, what in (
        ("--web", defaults.web, "STACK_WEB: serve the portal"),
        ("--ros", defaults.ros, "STACK_ROS: roscore, simulated robot, demo agent"),
        ("--ros2", defaults.ros2, "STACK_ROS2: the simulated robot on ROS 2 (Cyclone DDS)"),
    ):
        run_parser.add_argument(
            flag, action=argparse.BooleanOptionalAction, default=default, help=what
        )
    args = parser.parse_args(argv)
    if args.command == "redis":
        return redis(defaults.redis_url, defaults.workdir / "redis")
    if not is_loopback(args.host) and not args.public_url:
        parser.error(
            f"PORTAL_HOST={args.host} listens beyond this machine: say where robots reach it, "
            "PORTAL_PUBLIC_URL=http://ADDRESS:PORT (its host is then allowed)"
        )
    if args.public_url and urlsplit(args.public_url).scheme not in ("http", "https"):
        parser.error(f"PORTAL_PUBLIC_URL must be an http:// or https:// URL, not {args.public_url}")
    if min(args.workers, args.verify_workers) < 1 or min(args.web_workers, args.web_threads) < 0:
        parser.error("--workers and --verify-workers must be at least 1")
    config = replace(
        defaults,
        workdir=args.workdir,
        host=args.host,
        public_url=args.public_url.rstrip("/"),
        port=args.port,
        anvil_port=args.anvil_port,
        block_time=args.block_time,
        queue=args.queue,
        workers=args.workers,
        verify_workers=args.verify_workers,
        web_workers=args.web_workers,
        web_threads=args.web_threads,
        web=args.web,
        ros=args.ros,
        ros2=args.ros2,
    )
    return run(config)
