"""Robot signatures against none (issue 34; no paper figure): what signing costs the agent, the
portal's ingest and the check at every view, each against unsigned envelopes measured in the
same run (the baseline), and whether issue 13's ingest and view goals still hold with
signatures. Three variants: `unsigned` (robots added by hand), `signed` (provenance v1: one SM2
signature per record) and `v2` (provenance v2: one signature per upload batch, here per POST of
100, each header carrying its `topic_seq`, counted per robot and topic from 0).

- agent, in this process before any stack starts: ros_agent.wrapping.Recorder, the agent's one
  way from a message to the spool (extract, Fig. 4 record, seal under the owner's key, for a
  paired robot sign with its pairing key, append durably to the spool), records one message
  after another for A seconds: the simulated robot's nav_msgs/Odometry and its 320x240
  sensor_msgs/Image (PNG-encoded by the extractor). Unsigned is a robot set up by hand (no
  pairing key), signed a paired one. Envelopes/s; each round measures every kind and variant,
  the order of the variants turning by round; the figure is the median round's. The Recorder
  signs per record (v1): the agent's v2 path (sealing a batch once at upload) is not in it, so
  v2 has no Recorder figure here; sealing alone is measured for all three instead: 1 KB
  records sealed (and signed, per record or per batch of 100) one batch after another.
- then one fresh `make run` stack (bench/stack.py: gunicorn as make run serves it, anvil with
  automine, ANCHOR_MODE=root, make run's), K owners registered on chain, each with robots
  added by hand (unsigned) and robots paired through the pairing services (the owner approves
  the request; the workers add each key on chain from the owner's EOA, and the benchmark waits
  until every key is confirmed, as anchoring does).
- ingest, as bench/roots.py measures it (roots.upload_phase): C clients, one robot each, POST
  batches of 100 sealed 1 KB envelopes as fast as they are answered for D seconds, then every
  record is awaited on chain. Ingest = envelopes accepted / first POST to last answer. Each
  round runs the unsigned clients and the signed ones (order alternating); the figure is the
  median round's. With each phase the web's CPU per envelope, and how much of the machine's
  CPU went to processes outside the stack and the benchmark (the other work on this machine).
- view, idle: V views of anchored unsigned records and V of signed ones, alternating one after
  another (roots.view_times: `GET /api/v1/records/{id}/content/`, the owner's token; the worker
  checks the record at every view; for a signed one also robotKeyOf and the SM2 signature).
  p50 and p95 of each.
- view under load (roots.views_under_load): for each variant, views of its records while one
  robot of that variant uploads 100 records/s (10 per POST every 0.1 s), L/R seconds per round;
  p50 and p95 over the rounds.
- the worker's check alone (sharing.verification.check.records_verify, in this process against the
  stack's chain and storage), one record at a time, the variants alternating; and of 100 records
  of one upload batch at once (a page, an export's batch: claims_hold verifies a v2 batch's
  signature once); and SM2 sign and verify of one record's signature message on one core
  (smcrypto.sm2's backend named in the results): where a signed view's extra time goes.

Until the portal's ingest verifies a v2 batch's signature once, it verifies each v2 record's on
its own: v2's ingest figures here are from before that change.

Ratios are each variant's over unsigned of this run. Issue 13's goals (bench/roots.py GOALS:
ingest of 1 KB envelopes at least 1,500/s, idle view p50 at most 20 ms, view p95 at 100
records/s at most 250 ms) are judged for each variant. These are figures, not assertions.

Run: `python -m bench signing [--quick]`. Writes bench/results/signing.json, signing.csv and
signing.png.
"""

import argparse
import base64
import copy
import itertools
import os
import shutil
import statistics
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import psutil

from bench import MAKE_RUN_ANCHOR_MAX_WAIT, now_iso, run_in_child, summarize
from bench.common import add_ratios, print_table, record_plaintext, seal_batch, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.rest import add_arguments, check_arguments, report_header
from bench.roots import (
    BATCH,
    GOALS,
    PLAINTEXT_BYTES,
    Client,
    clients_create,
    upload_phase,
    view_figures,
    view_times,
    viewer_token,
    views_under_load,
)
from bench.stack import BenchStack, StackOptions, owners_register, run_finished
from ros_agent.sealing import RobotSigningKey

NAME = "signing"
VARIANTS = ("unsigned", "signed", "v2")  # the first is the baseline; signed is provenance v1
AGENT_KINDS = ("odometry", "image")
WORKER_CHECKS = 60  # record_verify calls per variant
WORKER_BATCH_CHECKS = 3  # checks of one upload batch's BATCH records at once, per variant
SM2_REPEAT = 300
# Issue 13's goals that signing could move (bench/roots.py measures them all).
GOAL_KEYS = ("ingest_per_s", "view_idle_p50_ms", "view_load_p95_ms")
ISSUE_13_GOALS = {key: GOALS[key] for key in GOAL_KEYS}
NOTES = [
    "signed is provenance v1 (one SM2 signature per record), v2 one per upload batch (here a "
    "POST of 100; at 100 records/s a POST of 10); the agent's Recorder signs per record, so v2 "
    "has sealing figures but no Recorder figures.",
    "until the portal's ingest verifies a v2 batch's signature once, it verifies each v2 "
    "record's on its own: v2's ingest figures are from before that change. The worker's check "
    "of a whole upload batch (batch ms/rec) already verifies a v2 batch once.",
    "ingest = envelopes answered 201 / first POST to last answer of a phase; a phase ends "
    "after its seconds or when its clients have sent every body sealed for it (enough for "
    "4,000 envelopes/s, bench/roots.py), whichever comes first: ingest_seconds_rounds says "
    "how long each lasted.",
    "others' share = CPU time of processes outside the stack and this benchmark (Redis's own "
    "server included, and whatever else runs on the machine) over the phase's wall time and "
    "all cores.",
    "every process (anvil, the web server, workers, beat, Redis and the clients) shares this "
    "machine, and other work may run on it: see load_average_at_start and _at_end.",
]
HIGHER_IS_BETTER = ("ingest_per_s",)  # of ISSUE_13_GOALS; the view goals are ceilings
RATIO_KEYS = (
    "agent_odometry_per_s",
    "agent_image_per_s",
    "seal_per_s",
    "ingest_per_s",
    "ingest_web_cpu_ms_per_envelope",
    "view_idle_p50_ms",
    "view_idle_p95_ms",
    "view_load_p50_ms",
    "view_load_p95_ms",
    "worker_check_p50_ms",
    "worker_check_batch_ms_per_record",
)
FIELDS = (
    "signing",
    "envelope_bytes",
    *RATIO_KEYS,
    *(f"{key}_ratio_vs_unsigned" for key in RATIO_KEYS),
)
COLUMNS = (
    ("variant", "signing", ""),
    ("odom/s", "agent_odometry_per_s", ".0f"),
    ("image/s", "agent_image_per_s", ".1f"),
    ("seal/s", "seal_per_s", ".0f"),
    ("ingest/s", "ingest_per_s", ".0f"),
    ("web ms/env", "ingest_web_cpu_ms_per_envelope", ".3f"),
    ("view p50", "view_idle_p50_ms", ".1f"),
    ("view p95", "view_idle_p95_ms", ".1f"),
    ("load p95", "view_load_p95_ms", ".1f"),
    ("check p50", "worker_check_p50_ms", ".2f"),
    ("batch ms/rec", "worker_check_batch_ms_per_record", ".3f"),
)


@dataclass(frozen=True)
class SigningRun:
    """The portal part of the run: one stack, every phase on it."""

    clients: int
    owners: int
    rounds: int
    ingest_seconds: float
    views: int
    load_seconds: float
    workers: int
    web_workers: int
    max_wait: float
    timeout: float
    redis_url: str
    keep_logs: bool
    block_time: float | None = None
    batch_max: int = 100

    def describe(self) -> str:
        return (
            f"ANCHOR_MODE=root: {self.rounds} rounds of {self.clients} clients x {BATCH}-envelope "
            f"POSTs for {self.ingest_seconds:g}s per variant, {self.views} idle views and "
            f"{self.load_seconds:g}s at 100 records/s per variant"
        )

    def stack_options(self) -> StackOptions:
        return StackOptions.for_run(self, web_workers=self.web_workers, anchor_mode="root")


# --- what the figures are made of (pure) ------------------------------------------------------


def round_orders(rounds: int, variants: Sequence[str] = VARIANTS) -> Iterator[tuple[str, ...]]:
    """The variants' order in each round, turned by one each round (unsigned first, then
    signed, then v2), so that none always runs on the busier (fuller, later) stack or
    machine; two variants simply swap."""
    for number in range(rounds):
        turn = number % len(variants)
        yield (*variants[turn:], *variants[:turn])


def median_round(rates: Sequence[float | None]) -> float | None:
    """The figure of several rounds: their median (None if a round measured nothing)."""
    measured = [rate for rate in rates if rate is not None]
    if not measured or len(measured) < len(rates):
        return None
    return statistics.median(measured)


def interleaved(*lists: Sequence[str]) -> list[str]:
    """first[0], second[0], ..., first[1], second[1], ... as long as all last: views of the
    variants one after another, so that whatever else loads the machine loads all alike."""
    return [item for row in zip(*lists, strict=False) for item in row]


def split_times(
    ids: Sequence[str], times: Sequence[float], groups: dict[str, set[str]]
) -> dict[str, list[float]]:
    """The milliseconds of views taken round and round `ids` (view_times), by the group each
    viewed id belongs to."""
    split: dict[str, list[float]] = {name: [] for name in groups}
    for number, elapsed in enumerate(times):
        viewed = ids[number % len(ids)]
        for name, members in groups.items():
            if viewed in members:
                split[name].append(elapsed)
    return split


def goals_met(row: dict[str, Any]) -> dict[str, bool | None]:
    """Each of issue 13's goals signing could move: met, not met, or not measured."""
    met: dict[str, bool | None] = {}
    for key, goal in ISSUE_13_GOALS.items():
        value = row.get(key)
        met[key] = (
            None if value is None else (value >= goal if key in HIGHER_IS_BETTER else value <= goal)
        )
    return met


def ratios(rows: list[dict[str, Any]]) -> None:
    """Each row's RATIO_KEYS over the unsigned row's, as "<key>_ratio_vs_unsigned"."""
    add_ratios(
        rows,
        (),
        {key: f"{key}_ratio_vs_unsigned" for key in RATIO_KEYS},
        baseline=lambda row: row["signing"] == "unsigned",
    )


def others_share(
    *, machine_busy_s: float, ours_s: float, wall_s: float, cores: int
) -> float | None:
    """The share of the machine's cores busy with work that is neither the stack's nor the
    benchmark's over a phase (another engineer's tests, say); None over no time."""
    if wall_s <= 0 or cores < 1:
        return None
    return max(0.0, machine_busy_s - ours_s) / (wall_s * cores)


# --- the agent, in this process -----------------------------------------------------------------


# The variants the agent's Recorder seals (it signs per record: v1); v2's is sealing alone.
RECORDER_VARIANTS = ("unsigned", "signed")


def agent_rates(seconds: float, rounds: int) -> dict[str, dict[str, Any]]:
    """Envelopes/s through the agent's Recorder for each kind of message and variant it has,
    and sealed alone for every variant: the median round's, and every round's."""
    from ros_agent import sim
    from smcrypto import sm2, sm4

    key = sm4.generate_key()
    signing_key = RobotSigningKey.of(sm2.generate_keypair()[0])
    signing_keys = {"unsigned": None, "signed": signing_key, "v2": signing_key}
    messages = _agent_messages(sim)
    measured: dict[str, dict[str, list[float]]] = {
        variant: {kind: [] for kind in AGENT_KINDS} for variant in RECORDER_VARIANTS
    }
    sealed: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
    for order in round_orders(rounds):
        for kind in AGENT_KINDS:
            for variant in (variant for variant in order if variant in RECORDER_VARIANTS):
                rate = _recorder_rate(messages[kind], key, signing_keys[variant], seconds)
                measured[variant][kind].append(rate)
        for variant in order:
            sealed[variant].append(seal_rate(variant, key, signing_keys[variant], seconds))
    rows: dict[str, dict[str, Any]] = {
        variant: {"seal_per_s": median_round(rates), "seal_per_s_rounds": rates}
        for variant, rates in sealed.items()
    }
    for variant, kinds in measured.items():
        rows[variant] |= {
            **{f"agent_{kind}_per_s": median_round(rates) for kind, rates in kinds.items()},
            **{f"agent_{kind}_per_s_rounds": rates for kind, rates in kinds.items()},
        }
    return rows


def seal_rate(
    variant: str, key: bytes, signing_key: RobotSigningKey | None, seconds: float
) -> float:
    """1 KB records sealed per second, BATCH at a time for `seconds`: unsigned, signed one by
    one (v1, ros_agent.sealing) or signed once per batch (v2, bench.common.seal_batch). The
    records are made before the clock starts."""
    from ros_agent import sealing

    robot = SimpleNamespace(id=uuid.uuid4(), owner=SimpleNamespace(username="bench-owner"))
    records = [record_plaintext(robot, seq=seq) for seq in range(1, BATCH + 1)]

    def one_batch(first_topic_seq: int) -> None:
        if variant == "v2":
            seal_batch(key, records, signing_key, first_topic_seq=first_topic_seq)
        else:
            for header, plaintext in records:
                sealing.seal_record(key, header, plaintext, signing_key)

    one_batch(0)  # warm: key objects made and cached
    started = time.perf_counter()
    for batches in itertools.count(1):
        one_batch(batches * BATCH)
        elapsed = time.perf_counter() - started
        if elapsed >= seconds:
            return batches * BATCH / elapsed
    raise AssertionError("itertools.count does not end")


def _agent_messages(sim: Any) -> dict[str, tuple[list[Any], str, str]]:
    """A few of the simulated robot's messages of each kind, stamped (their time is their
    capture time), with the topic and type the agent records them under."""
    import genpy

    stamp = genpy.Time(1_763_733_600, 0)
    odometry = [sim.odometry_message(sim.figure_eight(t / 10), stamp) for t in range(50)]
    images = [sim.image_message(sim.draw_scene(frame), stamp) for frame in range(5)]
    return {
        "odometry": (odometry, sim.ODOM_TOPIC, "nav_msgs/Odometry"),
        "image": (images, sim.IMAGE_TOPIC, "sensor_msgs/Image"),
    }


def _recorder_rate(
    messages: tuple[list[Any], str, str],
    key: bytes,
    signing_key: RobotSigningKey | None,
    seconds: float,
) -> float:
    """Messages recorded per second, one after another for `seconds` (after a few to warm up),
    into a spool of its own in a fresh folder (removed after)."""
    from ros_agent.counters import AgentCounters
    from ros_agent.spool import Spool
    from ros_agent.wrapping import Recorder

    msgs, topic, ros_type = messages
    folder = Path(tempfile.mkdtemp(prefix="authros-bench-signing-spool-"))
    spool = Spool(folder, max_bytes=2**40)
    counters = AgentCounters()
    recorder = Recorder(
        spool=spool,
        owner="bench-owner",
        robot=str(uuid.uuid4()),
        counters=counters,
        key=key,
        signing_key=signing_key,
    )
    try:
        for msg in msgs[:3]:
            recorder.record(msg, topic=topic, ros_type=ros_type)
        started = time.perf_counter()
        for recorded, msg in enumerate(itertools.cycle(msgs), 1):
            if recorder.record(msg, topic=topic, ros_type=ros_type) is None:
                raise RuntimeError(f"the recorder did not spool a {ros_type}: {counters}")
            elapsed = time.perf_counter() - started
            if elapsed >= seconds:
                return recorded / elapsed
        raise AssertionError("itertools.cycle ends only on an empty list")
    finally:
        recorder.close()
        spool.close()
        shutil.rmtree(folder, ignore_errors=True)


def sm2_backend() -> str:
    """smcrypto.sm2's backend in this process (the stack's processes choose theirs alike)."""
    from smcrypto import sm2

    return sm2.BACKEND


def sm2_costs_by_backend(repeat: int = SM2_REPEAT) -> dict[str, dict[str, float]]:
    """sm2_costs in a fresh interpreter for each SM2 backend that imports here, chosen as an
    operator chooses it (AUTHROS_SM2_BACKEND): what a robot or an auditor without Tongsuo
    (an ARM64 one) pays per record signed and verified, and per batch signed."""
    from smcrypto import sm2

    costs = {}
    saved = os.environ.get(sm2.BACKEND_VARIABLE)
    try:
        for name in sm2.BACKENDS:
            try:
                sm2.backend_load(name)
            except ImportError:
                continue
            os.environ[sm2.BACKEND_VARIABLE] = name
            costs[name] = run_in_child(sm2_costs, repeat)
    finally:
        if saved is None:
            os.environ.pop(sm2.BACKEND_VARIABLE, None)
        else:
            os.environ[sm2.BACKEND_VARIABLE] = saved
    return costs


def sm2_costs(repeat: int = SM2_REPEAT) -> dict[str, float]:
    """SM2 sign and verify of one 1 KB record's signature message (smcrypto.provenance), and
    the signing of a v2 batch of BATCH such records, on one core: milliseconds, median of
    `repeat` (of a tenth as many for the batch)."""
    from smcrypto import provenance, sm2

    private_key, public_key = sm2.generate_keypair()
    header = {"owner": "bench-owner", "robot": str(uuid.uuid4()), "topic": "/robot/odom"}
    header |= {"type": "nav_msgs/Odometry", "seq": 1, "time": "2026-11-28T12:00:00Z"}
    plaintext = b"x" * PLAINTEXT_BYTES
    signed = provenance.sign_header(private_key, public_key, header, plaintext)

    def timed(operation: Callable[[], object], times: int = repeat) -> float:
        samples = []
        for _ in range(times):
            started = time.perf_counter_ns()
            operation()
            samples.append((time.perf_counter_ns() - started) / 1e6)
        return statistics.median(samples)

    batch = [({**header, "seq": seq, "topic_seq": seq}, plaintext) for seq in range(BATCH)]
    return {
        "sm2_sign_header_ms": timed(
            lambda: provenance.sign_header(private_key, public_key, header, plaintext)
        ),
        "sm2_verify_header_ms": timed(
            lambda: provenance.verify_header(public_key, signed, plaintext)
        ),
        # v2: the tree of BATCH leaves and its one signature, per batch
        "sm2_sign_batch_ms": timed(
            lambda: provenance.sign_batch(private_key, public_key, batch), max(repeat // 10, 1)
        ),
    }


# --- the portal, in a child process with a fresh stack -----------------------------------------


class CpuWatch:
    """Where the CPU went over one phase: the web's, the whole stack's, this process's (the
    clients), and the machine's busy time beyond those (others' work on this machine)."""

    def __init__(self, stack: BenchStack) -> None:
        self.stack = stack
        self.stack_before = stack.cpu_seconds()
        self.machine_before = psutil.cpu_times()
        self.own_before = psutil.Process().cpu_times()
        self.started = time.monotonic()

    def stop(self) -> dict[str, float | None]:
        stack_after, machine_after = self.stack.cpu_seconds(), psutil.cpu_times()
        own_after = psutil.Process().cpu_times()
        wall = time.monotonic() - self.started
        stack_used = {
            role: stack_after[role] - self.stack_before.get(role, 0.0) for role in stack_after
        }
        own = own_after.user + own_after.system - self.own_before.user - self.own_before.system
        busy = (sum(machine_after) - machine_after.idle - getattr(machine_after, "iowait", 0.0)) - (
            sum(self.machine_before)
            - self.machine_before.idle
            - getattr(self.machine_before, "iowait", 0.0)
        )
        return {
            "wall_s": wall,
            "web_cpu_s": stack_used.get("web", 0.0),
            "stack_cpu_s": sum(stack_used.values()),
            "bench_cpu_s": own,
            "others_share": others_share(
                machine_busy_s=busy,
                ours_s=sum(stack_used.values()) + own,
                wall_s=wall,
                cores=psutil.cpu_count() or 1,
            ),
        }


def measure(run: SigningRun) -> dict[str, Any]:
    """Every portal phase on one fresh stack; the rows of both variants."""
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-signing-"))
    stack = BenchStack(run.stack_options(), workdir)
    try:
        stack.start()
        robots = owners_register(stack, run.owners)
        clients = {
            "unsigned": clients_create(robots, run.clients),
            "signed": _paired_clients(stack, robots, run.clients),
            "v2": _paired_clients(stack, robots, run.clients, batched=True),
        }
        rows: dict[str, dict[str, Any]] = {variant: {"signing": variant} for variant in VARIANTS}
        _ingest(stack, run, clients, rows)
        owner = robots[0][0].owner
        viewer = viewer_token(owner)
        _idle_views(stack, run, clients, owner, viewer, rows)
        _load_views(stack, run, clients, owner, viewer, rows)
        _worker_checks(clients, owner, rows)
        found = {"variants": [rows[variant] for variant in VARIANTS]}
        found["anchor_quiet_s"] = stack.portal_settings["anchor_quiet"]
    finally:
        stack.stop()
    return run_finished(found, stack, keep_logs=run.keep_logs)


@dataclass
class BatchClient(Client):
    """A paired robot that signs each upload batch once (provenance v2): each POST's envelopes
    are one batch, their `topic_seq` counting on from 0 for the robot's one topic. Bodies
    sealed for a phase but not sent (it ends by time) leave their numbers unused, as records
    an agent lost would: gaps, never a number used twice."""

    next_topic_seq: int = 0

    def bodies(self, count: int, per_post: int) -> list[dict[str, list[str]]]:
        """`count` POST bodies of `per_post` envelopes, each body one batch, sealed now."""
        bodies = []
        for _ in range(count):
            records = [
                record_plaintext(
                    self.robot, seq=self.next_seq + number, plaintext_bytes=PLAINTEXT_BYTES
                )
                for number in range(per_post)
            ]
            sealed = seal_batch(
                self.key, records, self.signing_key, first_topic_seq=self.next_topic_seq
            )
            self.next_seq += per_post
            self.next_topic_seq += per_post
            bodies.append({"envelopes": [base64.b64encode(data).decode() for data in sealed]})
        return bodies


def _paired_clients(
    stack: BenchStack, robots: list[tuple[Any, bytes]], count: int, *, batched: bool = False
) -> list[Client]:
    """`count` robots paired as the agent pairs (its SM2 key pair made here, the request
    approved by the owner), round-robin over the owners, signing per record or, `batched`,
    per upload batch (v2); returned once the workers confirmed every robot's key on chain."""
    from accounts.models import ChainState, Robot
    from accounts.services.pairing import robot_pairing_answer, robot_pairing_request
    from smcrypto import sm2

    made = []
    for number in range(count):
        robot, key = robots[number % len(robots)]
        owner = robot.owner
        private_key, public_key = sm2.generate_keypair()
        name = f"{'v2' if batched else 'signed'}-{number}"
        pairing, _secret = robot_pairing_request(name=name, public_key=public_key)
        pairing = robot_pairing_answer(
            owner=owner, code=pairing.code, approve=True, actor=owner.user
        )
        token = sm2.decrypt(private_key, pairing.token_sm2).decode("ascii")
        paired = Robot.objects.select_related("owner").get(pk=pairing.robot_id)
        kind = BatchClient if batched else Client
        made.append(kind(paired, key, token, signing_key=RobotSigningKey.of(private_key)))
    pks = [client.robot.pk for client in made]

    def confirmed() -> bool:
        states = list(Robot.objects.filter(pk__in=pks).values_list("key_chain_state", flat=True))
        if ChainState.FAILED in states:
            raise RuntimeError(f"a robot key could not be registered on chain:\n{stack.log_tail()}")
        return states.count(ChainState.CONFIRMED) == len(pks)

    stack.wait_for(confirmed, "robot keys not on chain")
    return made


def _ingest(
    stack: BenchStack,
    run: SigningRun,
    clients: dict[str, list[Client]],
    rows: dict[str, dict[str, Any]],
) -> None:
    """Each round, each variant's clients flat out for run.ingest_seconds (roots.upload_phase),
    every record awaited on chain after each phase."""
    phases: dict[str, list[dict[str, Any]]] = {variant: [] for variant in VARIANTS}
    for order in round_orders(run.rounds):
        for variant in order:
            print(f"== ingest, {variant}", file=sys.stderr, flush=True)
            watch = CpuWatch(stack)
            phase = upload_phase(
                stack, clients[variant], seconds=run.ingest_seconds, rate=None, timeout=run.timeout
            )
            phases[variant].append(phase | watch.stop())
    for variant, done in phases.items():
        rates = [phase["uploaded"] / phase["seconds"] for phase in done]
        accepted = sum(phase["uploaded"] for phase in done)
        rows[variant] |= {
            "ingest_per_s": median_round(rates),
            "ingest_per_s_rounds": rates,
            "ingest_seconds_rounds": [phase["seconds"] for phase in done],
            "ingested": accepted,
            "ingest_refused": [refusal for phase in done for refusal in phase["refused"]][:5],
            "ingest_web_cpu_ms_per_envelope": (
                sum(phase["web_cpu_s"] for phase in done) * 1000 / accepted if accepted else None
            ),
            "ingest_others_share_rounds": [phase["others_share"] for phase in done],
            "ingest_anchored": sum(phase["anchored"] for phase in done),
            "ingest_failed": sum(phase["failed"] for phase in done),
            "ingest_pending_at_timeout": sum(phase["pending"] for phase in done),
            "ingest_latency_p95_s_rounds": [phase["latency_p95_s"] for phase in done],
            "envelope_bytes": _envelope_bytes(clients[variant][0]),
        }


def _envelope_bytes(client: Client) -> int:
    """The size of one of the client's sealed 1 KB envelopes in a POST of BATCH (sealed here
    by a copy of the client, never sent: its numbers are not used up)."""
    return len(base64.b64decode(copy.copy(client).bodies(1, BATCH)[0]["envelopes"][0]))


def _variant_ids(clients: Sequence[Client], owner: Any, limit: int) -> list[str]:
    """Anchored records of the owner's uploaded by these clients (one variant's), in random
    order."""
    from sharing.models import Record

    chosen = Record.objects.filter(
        owner=owner,
        robot__in=[client.robot.pk for client in clients],
        status=Record.Status.ANCHORED,
    )
    return [str(pk) for pk in chosen.values_list("pk", flat=True).order_by("?")[:limit]]


def _idle_views(
    stack: BenchStack,
    run: SigningRun,
    clients: dict[str, list[Client]],
    owner: Any,
    viewer: str,
    rows: dict[str, dict[str, Any]],
) -> None:
    """run.views views of each variant's records, the variants alternating, nothing else
    running."""
    ids = {variant: _variant_ids(clients[variant], owner, run.views) for variant in VARIANTS}
    order = interleaved(*(ids[variant] for variant in VARIANTS))
    print(f"== {len(order)} idle views", file=sys.stderr, flush=True)
    watch = CpuWatch(stack)
    times, failed = view_times(stack.web_url, viewer, order)
    others = watch.stop()["others_share"]
    members = {variant: set(ids[variant]) for variant in VARIANTS}
    by_variant = split_times(order, times, members)
    for variant in VARIANTS:
        errors = sum(pk in members[variant] for pk in failed)
        rows[variant] |= view_figures(by_variant[variant], errors, "idle") | {
            "idle_others_share": others
        }


def _load_views(
    stack: BenchStack,
    run: SigningRun,
    clients: dict[str, list[Client]],
    owner: Any,
    viewer: str,
    rows: dict[str, dict[str, Any]],
) -> None:
    """Each round, each variant: its records viewed while one of its robots uploads 100
    records/s (roots.views_under_load) for run.load_seconds / run.rounds."""
    seconds = run.load_seconds / run.rounds
    times: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
    failures = dict.fromkeys(VARIANTS, 0)
    latency: dict[str, list[float | None]] = {variant: [] for variant in VARIANTS}
    others: dict[str, list[float | None]] = {variant: [] for variant in VARIANTS}
    for order in round_orders(run.rounds):
        for variant in order:
            print(f"== views at 100 records/s, {variant}", file=sys.stderr, flush=True)
            watch = CpuWatch(stack)
            viewed, failed, phase = views_under_load(
                stack,
                clients[variant][0],
                viewer,
                _variant_ids(clients[variant], owner, 2000),
                seconds=seconds,
                timeout=run.timeout,
            )
            others[variant].append(watch.stop()["others_share"])
            times[variant] += viewed
            failures[variant] += len(failed)
            latency[variant].append(phase.get("latency_p95_s"))
    for variant in VARIANTS:
        rows[variant] |= view_figures(times[variant], failures[variant], "load") | {
            "load_latency_p95_s_rounds": latency[variant],
            "load_others_share_rounds": others[variant],
        }


def _worker_checks(
    clients: dict[str, list[Client]], owner: Any, rows: dict[str, dict[str, Any]]
) -> None:
    """The worker's check alone (records_verify, in this process): one record at a time, the
    variants alternating, WORKER_CHECKS of each, milliseconds and every verdict kept; then the
    BATCH records of one upload (one POST: for v2 one batch signature) checked at once,
    WORKER_BATCH_CHECKS times per variant in turn, milliseconds per record."""
    from sharing.models import Record
    from sharing.verification.check import records_verify

    ids = {variant: _variant_ids(clients[variant], owner, WORKER_CHECKS) for variant in VARIANTS}
    order = interleaved(*(ids[variant] for variant in VARIANTS))
    for record_id in order[:4]:  # warm: the first calls open connections
        records_verify(record_ids=[record_id], viewer_id=owner.pk)[0]
    times: list[float] = []
    outcomes: dict[str, set[str]] = {variant: set() for variant in VARIANTS}
    members = {variant: set(ids[variant]) for variant in VARIANTS}
    for record_id in order:
        started = time.perf_counter()
        verification = records_verify(record_ids=[record_id], viewer_id=owner.pk)[0]
        times.append((time.perf_counter() - started) * 1000)
        variant = next(name for name, pks in members.items() if record_id in pks)
        outcomes[variant].add(str(verification.verdict.outcome))
    for variant, checked in split_times(order, times, members).items():
        stats = summarize(checked)
        rows[variant] |= {
            "worker_check_p50_ms": stats["median_ms"],
            "worker_check_p95_ms": stats["p95_ms"],
            "worker_checks": len(checked),
            "worker_check_outcomes": sorted(outcomes[variant]),
        }
    batches = {}
    for variant in VARIANTS:
        robot = next(client.robot for client in clients[variant] if client.robot.owner == owner)
        first_post = Record.objects.filter(robot=robot, seq__range=(1, BATCH))
        batches[variant] = [str(pk) for pk in first_post.values_list("pk", flat=True)]
    per_record: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
    batch_outcomes: dict[str, set[str]] = {variant: set() for variant in VARIANTS}
    for order_of_round in round_orders(WORKER_BATCH_CHECKS):
        for variant in order_of_round:
            started = time.perf_counter()
            checked = records_verify(record_ids=batches[variant], viewer_id=owner.pk)
            elapsed = (time.perf_counter() - started) * 1000
            per_record[variant].append(elapsed / max(len(checked), 1))
            batch_outcomes[variant] |= {str(item.verdict.outcome) for item in checked}
    for variant in VARIANTS:
        rows[variant] |= {
            "worker_check_batch_ms_per_record": statistics.median(per_record[variant]),
            "worker_check_batch_records": len(batches[variant]),
            "worker_check_batch_outcomes": sorted(batch_outcomes[variant]),
        }


# --- the benchmark -----------------------------------------------------------------------------


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench signing", description=__doc__)
    add_arguments(parser)
    parser.add_argument("--clients", type=int, default=4, help="ingest clients per variant (4)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of every phase (5)")
    parser.add_argument(
        "--ingest-seconds", type=float, default=6.0, help="flat out, per variant and round (6)"
    )
    parser.add_argument("--views", type=int, default=300, help="idle views per variant (300)")
    parser.add_argument(
        "--load-seconds",
        type=float,
        default=30.0,
        help="views at 100 records/s, per variant, split over the rounds (30)",
    )
    parser.add_argument(
        "--agent-seconds",
        type=float,
        default=2.0,
        help="recording, per kind, variant and round (2)",
    )
    parser.set_defaults(max_wait=MAKE_RUN_ANCHOR_MAX_WAIT)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    if args.quick:
        args.rounds, args.ingest_seconds, args.views = 2, 3.0, 30
        args.load_seconds, args.agent_seconds = 6.0, 1.0
    if args.rounds < 1 or args.clients < 1 or args.views < 1:
        parser.error("--rounds, --clients and --views must be at least 1")
    if min(args.ingest_seconds, args.load_seconds, args.agent_seconds) <= 0:
        parser.error("--ingest-seconds, --load-seconds and --agent-seconds must be positive")
    started = now_iso()
    report = report_header(NAME, args, started)
    print("== agent: Recorder (unsigned, signed) and sealing alone (and v2)", flush=True)
    agent = agent_rates(args.agent_seconds, args.rounds)
    crypto = sm2_costs()
    by_backend = sm2_costs_by_backend()
    run = SigningRun(
        clients=args.clients,
        owners=min(args.owners, args.clients),
        rounds=args.rounds,
        ingest_seconds=args.ingest_seconds,
        views=args.views,
        load_seconds=args.load_seconds,
        workers=args.workers,
        web_workers=args.web_workers,
        max_wait=args.max_wait,
        timeout=args.timeout,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
    )
    print(f"== {run.describe()}", flush=True)
    portal = run_in_child(measure, run)
    rows = [agent[row["signing"]] | row for row in portal.pop("variants")]
    ratios(rows)
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    report["settings"] |= {
        "agents": f"{args.clients} clients per variant, one robot each, round-robin over "
        f"{run.owners} owners, each a thread with its own requests.Session posting "
        f"{BATCH} envelopes per POST /api/v1/records/ (Authorization: Token)",
        "clients": args.clients,
        "rounds": args.rounds,
        "batch_per_post": BATCH,
        "plaintext_bytes": PLAINTEXT_BYTES,
        "ingest_seconds": args.ingest_seconds,
        "idle_views": args.views,
        "load_seconds": args.load_seconds,
        "agent_seconds": args.agent_seconds,
        "anchor_mode": "root",
        "anchor_quiet_s": portal.get("anchor_quiet_s"),
        "chain": "anvil, automine",
        "variants": list(VARIANTS),
        "sm2_backend": sm2_backend(),
    }
    report["notes"] = NOTES
    report["sm2"] = crypto
    report["sm2_by_backend"] = by_backend
    report["goals"] = ISSUE_13_GOALS
    report["results"] = rows
    report["goals_met"] = {row["signing"]: goals_met(row) for row in rows}
    report["worker_logs"] = portal.get("worker_logs")
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = {row["signing"]: row for row in report["results"]}
    variants = [variant for variant in VARIANTS if variant in rows]
    panels = (
        ("agent, envelopes/s", ("agent_odometry_per_s", "agent_image_per_s", "seal_per_s"), "log"),
        ("ingest, 1 KB envelopes/s", ("ingest_per_s",), "linear"),
        (
            "verified view, ms",
            ("view_idle_p50_ms", "view_idle_p95_ms", "view_load_p50_ms", "view_load_p95_ms"),
            "log",
        ),
        (
            "worker's check, ms per record",
            ("worker_check_p50_ms", "worker_check_batch_ms_per_record"),
            "log",
        ),
    )
    figure, axes = plt.subplots(1, len(panels), figsize=(16, 4), width_ratios=(3, 1, 4, 2))
    width = 0.8 / len(variants)
    for axis, (title, keys, scale) in zip(axes, panels, strict=True):
        for number, variant in enumerate(variants):
            row = rows[variant]
            values = [row.get(key) or 0 for key in keys]
            positions = [k + number * width for k in range(len(keys))]
            axis.bar(positions, values, width, label=variant)
        for k, key in enumerate(keys):
            if key in ISSUE_13_GOALS:
                axis.hlines(
                    ISSUE_13_GOALS[key],
                    k - width / 2,
                    k + width * len(variants) - width / 2,
                    colors="black",
                    linestyles="dashed",
                )
        axis.set_xticks(
            [k + width * (len(variants) - 1) / 2 for k in range(len(keys))], keys, fontsize=6
        )
        axis.set_yscale(scale)
        axis.set_title(title, fontsize=9)
    axes[0].legend(fontsize=7)
    backend = report.get("settings", {}).get("sm2_backend")
    save_figure(
        figure,
        path,
        "Robot signatures against none: v1 per record, v2 per batch (dashed: issue 13's goals)"
        + (f"; SM2 backend {backend}" if backend else "")
        + f"; {machine_line(report)}",
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
