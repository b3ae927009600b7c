"""`python -m ros_agent import --config agent.yaml FILE...`: seal recorded bags and upload them.

Reads ROS 1 `.bag` files, ROS 2 `.db3` and `.mcap` files and rosbag2 folders (rosbags), keeps
the topics the config names with the type it gives, and seals every message with its original
capture time (its header stamp, else the time the bag recorded it) into the robot's spool, the
same Recorder and Uploader as the live agent. A progress bar on stderr, a summary on stdout.

A file imported twice uploads nothing twice: the spool keeps an import ledger,
`imports/<sha256 of the content>.json`, with how many messages of each topic were handled.
A finished topic is skipped on the next import (under any file name); an interrupted import
continues where the ledger stops. The ledger is written on every stop and every LEDGER_EVERY
messages; after a hard kill between two writes, the next import asks the spool and the portal
(the robot's own records, by topic and capture time) whether each of the next LEDGER_EVERY
messages was sent already, so none is sent twice.

Imports and live capture share the robot's one sequence counter (the portal refuses a
number below the robot's last), so the import takes the spool: while the agent of that robot
runs, the import is refused with a message saying so.

Bad input never ends in a traceback: a file none of the readers can open is refused with the
reason (nothing of it spooled); a .bag or .mcap cut off before its index or summary (and
rosbag's `.bag.active` of a recorder that died) is read from the start up to the break
(ros_agent.salvage); a message that does not decode or convert is skipped and counted; a
file that breaks off part way keeps what was read before the break.
"""

import argparse
import contextlib
import hashlib
import json
import logging
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import requests

from ros_agent import LOGGER_NAME
from ros_agent.config import AgentConfig, ConfigError, TopicConfig, load_config
from ros_agent.extractors import iso_utc
from ros_agent.pipeline import CLEAR_TEXT_WARNING, pipeline_build, token_in_clear
from ros_agent.ros2msg import (
    MessageTypeUnknown,
    default_typestore,
    learn_message_types,
    ros1_name,
    ros1_view,
    ros2_name,
)
from ros_agent.salvage import salvage_reader
from ros_agent.spool import SpoolError, write_durably
from ros_agent.wrapping import capture_time
from smcrypto import envelope

logger = logging.getLogger(f"{LOGGER_NAME}.bags")

LEDGER_EVERY = 100
LEDGER_DIR = "imports"
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
ACTIVE_BAG = ".bag.active"  # what `rosbag record` writes until it closes the bag
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
# Stop filling the spool above this share of its bound until the uploader made room.
SPOOL_HIGH_WATER = 0.8


class CannotCheck(Exception):
    """What a cut-off import sent cannot be checked (the portal does not answer)."""


class ImportRefused(Exception):
    """A file cannot be imported at all; the message says why, for the user."""


@dataclass
class FileReport:
    """What one import did with one file."""

    path: Path
    digest: str = ""
    imported: int = 0
    sealed_bytes: int = 0
    topics: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    refused: str = ""
    stopped: str = ""
    note: str = ""

    def lines(self) -> list[str]:
        if self.refused:
            return [f"{self.path}: refused: {self.refused}"]
        lines = [
            f"{self.path}: {self.imported} message(s) sealed, {self.sealed_bytes} bytes"
            + (f" (sha256 {self.digest[:16]}...)" if self.digest else "")
        ]
        if self.note:
            lines.append(f"  note: {self.note}")
        lines += [f"  {topic}: {count}" for topic, count in sorted(self.topics.items())]
        lines += [f"  skipped {count}: {why}" for why, count in sorted(self.skipped.items())]
        if self.stopped:
            lines.append(f"  stopped: {self.stopped}")
        return lines


class ImportLedger:
    """Per file content: how many messages of each topic were handled, on disk in the spool."""

    def __init__(self, spool_dir: Path, digest: str) -> None:
        self._folder = Path(spool_dir) / LEDGER_DIR
        self._folder.mkdir(mode=0o700, exist_ok=True)
        self._name = f"{digest}.json"
        self.digest = digest
        try:
            self.state = json.loads((self._folder / self._name).read_text(encoding="utf-8"))
        except FileNotFoundError:
            self.state = {"sha256": digest, "topics": {}}
        except (OSError, ValueError) as exc:
            raise ImportRefused(
                f"the import ledger {self._folder / self._name} is unreadable: "
                f"{exc}; remove it to import the file again"
            ) from None

    def done(self, topic: str) -> int:
        return int(self.state["topics"].get(topic, {}).get("done", 0))

    def complete(self, topic: str) -> bool:
        return bool(self.state["topics"].get(topic, {}).get("complete", False))

    @property
    def cut_off(self) -> bool:
        """An import of this content stopped without writing its ledger (killed, a crash): up
        to LEDGER_EVERY messages after the ledger's counts may have been sent all the same."""
        return bool(self.state.get("running", False))

    def note(self, topic: str, *, done: int, complete: bool = False) -> None:
        entry = self.state["topics"].setdefault(topic, {})
        entry["done"] = done
        entry["complete"] = complete

    def save(self, source: Path, *, running: bool) -> None:
        self.state["running"] = running
        names = self.state.setdefault("names", [])
        if str(source) not in names:
            names.append(str(source))
        self.state["updated_at"] = datetime.now(UTC).isoformat()
        text = json.dumps(self.state, indent=1, sort_keys=True).encode()
        write_durably(self._folder, self._name, text)


def content_digest(path: Path) -> str:
    """SHA-256 of a recording's messages' files: the file, or a rosbag2 folder's storage files
    in order (not its metadata.yaml), so a one-file folder and its file are the same content."""
    if path.is_file():
        files = [path]
    else:
        files = sorted(p for p in path.iterdir() if p.is_file() and p.name != "metadata.yaml")
    digest = hashlib.sha256()
    for file in files:
        with file.open("rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


class BagImporter:
    """Seals recorded messages of the configured topics into a robot's spool and uploads them."""

    def __init__(
        self, config: AgentConfig, *, progress: bool = True, stall_timeout: float = 60.0
    ) -> None:
        self.config = config
        # Short waits: an import is watched, and it ends by waiting for the last upload.
        pipeline = pipeline_build(
            config,
            flush_interval=min(config.flush_interval, 0.2),
            backoff_max=min(config.backoff_max, 5.0),
        )
        self.counters, self.spool = pipeline.counters, pipeline.spool
        self.uploader, self.recorder = pipeline.uploader, pipeline.recorder
        self.topics = {_absolute(topic.name): topic for topic in config.topics}
        self.progress = progress
        self.stall_timeout = stall_timeout
        self.stopping = threading.Event()
        self._typestore = default_typestore(config.ros2_distro)
        for topic in config.topics:  # a type the file does not define may be in a .msg file
            with contextlib.suppress(MessageTypeUnknown):
                learn_message_types(
                    self._typestore, [ros2_name(topic.type)], config.msg_search_dirs
                )
        self._spooled: set[tuple[str, str]] | None = None  # (topic, time) of queued envelopes
        self._lookup = requests.Session()
        self._lookup.headers["Authorization"] = f"Token {config.token}"

    # --- the whole run ------------------------------------------------------------------------

    def run(self, paths: Sequence[Path], *, upload_timeout: float) -> list[FileReport]:
        if (host := token_in_clear(self.config.portal_url)) is not None:
            logger.warning(CLEAR_TEXT_WARNING, host)
        self.uploader.start()
        try:
            return [self.import_file(path) for path in paths if not self.stopping.is_set()]
        finally:
            self.recorder.close()
            self._wait_until_sent(upload_timeout)
            self.uploader.stop(self.config.shutdown_flush)
            self.spool.close()
            self._lookup.close()

    def _wait_until_sent(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while len(self.spool) and time.monotonic() < deadline and not self.stopping.is_set():
            self.uploader.notify()
            time.sleep(0.05)

    # --- one file -----------------------------------------------------------------------------

    def import_file(self, path: Path) -> FileReport:
        report = FileReport(path=path)
        try:
            self._check_path(path)
            report.digest = content_digest(path)
            ledger = ImportLedger(self.config.spool_dir, report.digest)
            self._import(path, ledger, report)
        except ImportRefused as exc:
            report.refused = str(exc)
        except OSError as exc:
            report.refused = f"cannot read it: {exc.strerror or exc}"
        except Exception as exc:  # a file no reader foresaw: refused, never a traceback
            logger.debug("importing %s failed", path, exc_info=True)
            report.refused = f"cannot be imported: {type(exc).__name__}: {_reason(exc)}"
        return report

    def _check_path(self, path: Path) -> None:
        if not path.exists():
            raise ImportRefused("no such file or folder")
        if path.is_dir():
            if not (path / "metadata.yaml").exists():
                raise ImportRefused("a folder must be a rosbag2 recording (with metadata.yaml)")
        elif path.suffix not in BAG_SUFFIXES and not path.name.endswith(ACTIVE_BAG):
            raise ImportRefused(
                f"{path.suffix or 'no suffix'}: not a recording; expected {', '.join(BAG_SUFFIXES)}"
            )

    def _import(self, path: Path, ledger: ImportLedger, report: FileReport) -> None:
        from rosbags.highlevel import AnyReader

        try:
            reader = AnyReader([path], default_typestore=self._typestore)
            reader.open()
        except Exception as exc:  # rosbags raises many kinds for a damaged file
            reader = self._salvage(path, exc)
            report.note = f"read without its index, which is damaged or missing ({_reason(exc)})"
        try:
            selected = self._select(reader, ledger, report)
            total = sum(max(conn.msgcount, 0) for conn in selected) - sum(
                ledger.done(topic) for topic in {_absolute(conn.topic) for conn in selected}
            )
            with _progress_bar(path, total, enabled=self.progress) as bar:
                self._read(reader, selected, ledger, report, bar)
        finally:
            with contextlib.suppress(Exception):
                reader.close()

    def _salvage(self, path: Path, refusal: Exception) -> Any:
        """A reader for what is left of a cut-off .bag or .mcap, or ImportRefused."""
        try:
            reader = salvage_reader(path, self._typestore, ros1=path.name.endswith(ACTIVE_BAG))
        except Exception:  # whatever the salvage trips over, the file is refused
            reader = None
        if reader is None or not reader.connections:
            raise ImportRefused(f"not a readable recording: {_reason(refusal)}")
        return reader

    def _select(self, reader: Any, ledger: ImportLedger, report: FileReport) -> list[Any]:
        """The connections to read: configured topic, configured type, a known definition."""
        self._complete_types(reader)
        selected = []
        for conn in reader.connections:
            topic = _absolute(conn.topic)
            wanted = self.topics.get(topic)
            count = max(conn.msgcount, 0)
            if wanted is None:
                report.skipped[f"topic {topic} is not in the config"] += count
            elif ros1_name(conn.msgtype) != wanted.type:
                report.skipped[
                    f"topic {topic} holds {ros1_name(conn.msgtype)}, the config says {wanted.type}"
                ] += count
            elif conn.msgtype not in reader.typestore.fielddefs:
                report.skipped[
                    f"unknown message type {conn.msgtype} on {topic}: "
                    "the file has no definition of it"
                ] += count
            elif ledger.complete(topic):
                report.skipped[f"topic {topic} was imported before (same file content)"] += count
            else:
                selected.append(conn)
        return selected

    def _complete_types(self, reader: Any) -> None:
        """Types the file does not define, taken from the ROS 2 type store where it has them."""
        known = reader.typestore.fielddefs
        missing = {
            name: fields for name, fields in self._typestore.fielddefs.items() if name not in known
        }
        with contextlib.suppress(Exception):
            reader.typestore.register(missing)

    def _read(
        self, reader: Any, selected: list[Any], ledger: ImportLedger, report: FileReport, bar: Any
    ) -> None:
        seen: Counter = Counter()  # messages of each topic read in this pass, in file order
        topics = {_absolute(conn.topic) for conn in selected}
        to_check = LEDGER_EVERY if ledger.cut_off else 0
        if selected:
            ledger.save(report.path, running=True)
        handled_since_save = 0
        messages: Iterator[tuple[Any, int, bytes]] = (
            reader.messages(connections=selected) if selected else iter(())
        )
        try:
            for conn, timestamp, rawdata in messages:
                topic = _absolute(conn.topic)
                seen[topic] += 1
                if seen[topic] <= ledger.done(topic):
                    continue  # handled by an earlier, interrupted import of this content
                if self.stopping.is_set():
                    report.stopped = "interrupted; importing the file again continues here"
                    seen[topic] -= 1
                    break
                if not self._room_in_spool():
                    report.stopped = (
                        "the spool is full and the portal does not take it; "
                        "import the file again later, it continues here"
                    )
                    seen[topic] -= 1
                    break
                msg = self._decode(reader, conn, topic, rawdata, report)
                if msg is not None:
                    captured_at = capture_time(msg, _bag_time(timestamp))
                    if to_check and self._sent_before(topic, captured_at):
                        report.skipped["sent by an earlier import that was cut off"] += 1
                    else:
                        self._seal(msg, topic, timestamp, report)
                to_check = max(to_check - 1, 0)
                ledger.note(topic, done=seen[topic])
                bar.update(1)
                handled_since_save += 1
                if handled_since_save >= LEDGER_EVERY:
                    ledger.save(report.path, running=True)
                    handled_since_save = 0
        except CannotCheck as exc:
            report.stopped = (
                f"an earlier import of this file was cut off, and what it sent cannot be checked "
                f"now ({exc}); import the file again when the portal answers"
            )
            ledger.save(report.path, running=True)  # the next run checks again
            return
        except Exception as exc:  # a damaged chunk or record part way through the file
            report.stopped = _damaged(sum(seen.values()), _reason(exc))
        if not report.stopped and getattr(reader, "damage", ""):
            report.stopped = _damaged(sum(seen.values()), reader.damage)
        if not report.stopped or report.stopped.startswith("the file is damaged or cut off"):
            # Read to its end, or to where nothing more can be read: all there is, imported.
            for topic in topics:
                ledger.note(topic, done=seen[topic], complete=True)
        ledger.save(report.path, running=False)

    def _decode(
        self, reader: Any, conn: Any, topic: str, rawdata: bytes, report: FileReport
    ) -> Any:
        """The message as the extractors read it, or None (counted) if it does not decode."""
        try:
            return ros1_view(reader.deserialize(rawdata, conn.msgtype))
        except Exception as exc:  # any decoding failure is this message's
            report.skipped[f"a {self.topics[topic].type} message on {topic} does not decode"] += 1
            logger.debug("cannot decode a %s message: %s", conn.msgtype, exc)
            return None

    def _seal(self, msg: Any, topic: str, timestamp: int, report: FileReport) -> None:
        wanted: TopicConfig = self.topics[topic]
        failed_before = self.counters.failed
        used_before = self.spool.used_bytes
        seq = self.recorder.record(
            msg, topic=topic, ros_type=wanted.type, received_at=_bag_time(timestamp)
        )
        if seq is None:
            if self.counters.failed > failed_before:
                report.skipped[f"a {wanted.type} message on {topic} cannot become a record"] += 1
            else:
                report.skipped["the spool had no room"] += 1
            return
        report.imported += 1
        report.topics[topic] += 1
        report.sealed_bytes += max(self.spool.used_bytes - used_before, 0)

    def _sent_before(self, topic: str, captured_at: datetime) -> bool:
        """Whether the robot's spool or the portal holds a record of `topic` captured then."""
        if self._spooled is None:
            self._spooled = set()
            for item in self.spool.peek(len(self.spool) or 1):
                header = envelope.read_header(item.envelope).header
                self._spooled.add((header["topic"], header["time"]))
        if (topic, iso_utc(captured_at)) in self._spooled:
            return True
        try:
            answer = self._lookup.get(
                self.config.records_url,
                params={
                    "topic": topic,
                    "since": iso_utc(captured_at),
                    "until": iso_utc(captured_at + timedelta(microseconds=1)),
                },
                timeout=self.config.request_timeout,
                verify=self.config.tls_verify,
            )
        except requests.RequestException as exc:
            raise CannotCheck(f"no answer from the portal: {exc}") from None
        if answer.status_code != 200:
            raise CannotCheck(f"the portal answered HTTP {answer.status_code}")
        try:
            return bool(answer.json()["results"])
        except (ValueError, KeyError, TypeError):
            raise CannotCheck("the portal's answer is not a list of records") from None

    def _room_in_spool(self) -> bool:
        """Wait while the spool is nearly full and the uploader still makes progress."""
        last_progress = time.monotonic()
        last_used = self.spool.used_bytes
        while self.spool.used_bytes > SPOOL_HIGH_WATER * self.spool.max_bytes:
            if self.stopping.is_set():
                return False
            self.uploader.notify()
            time.sleep(0.05)
            used = self.spool.used_bytes
            if used < last_used:
                last_progress, last_used = time.monotonic(), used
            elif time.monotonic() - last_progress > self.stall_timeout:
                return False
        return True


def _bag_time(timestamp: int) -> datetime:
    """A recording's timestamp (nanoseconds since 1970) as a UTC datetime (microseconds)."""
    return _EPOCH + timedelta(microseconds=timestamp // 1000)


def _damaged(read: int, reason: str) -> str:
    return (
        f"the file is damaged or cut off after message {read}: {reason}; "
        "the messages before it were imported"
    )


def _absolute(topic: str) -> str:
    return "/" + topic.lstrip("/~")


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) < 300 else text[:300] + "..."


@contextlib.contextmanager
def _progress_bar(path: Path, total: int, *, enabled: bool) -> Iterator[Any]:
    from tqdm import tqdm

    with tqdm(
        total=max(total, 0),
        desc=path.name,
        unit="msg",
        file=sys.stderr,
        disable=None if enabled else True,
        leave=True,
    ) as bar:
        yield bar


def summary_lines(reports: Sequence[FileReport], importer: BagImporter) -> list[str]:
    lines: list[str] = []
    for report in reports:
        lines += report.lines()
    stats = importer.counters.snapshot()
    queued = len(importer.spool)
    totals = Counter()
    for report in reports:
        totals.update(report.topics)
    refused = stats["failed"] - _conversion_failures(reports)
    lines.append(
        f"total: {sum(r.imported for r in reports)} message(s) sealed, "
        f"{sum(r.sealed_bytes for r in reports)} bytes, {len(totals)} topic(s); "
        f"uploaded {stats['sent']}, refused by the portal {refused}, "
        f"waiting in the spool {queued}"
    )
    if queued:
        lines.append(
            f"{queued} envelope(s) wait in {importer.spool.directory}: the agent or the next "
            "import sends them"
        )
    return lines


def _conversion_failures(reports: Sequence[FileReport]) -> int:
    return sum(
        count
        for report in reports
        for why, count in report.skipped.items()
        if why.endswith("cannot become a record")
    )


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent import",
        description="Seal recorded ROS 1 .bag, ROS 2 .db3 and .mcap files (or rosbag2 folders) "
        "with the robot's key and upload them to the portal.",
    )
    parser.add_argument("--config", type=Path, required=True, help="agent.yaml of the robot")
    parser.add_argument(
        "--upload-timeout",
        type=float,
        default=300.0,
        help="seconds to wait for the portal at the end (default 300); what is not sent "
        "stays in the spool",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("files", nargs="+", type=Path, metavar="FILE")
    args = parser.parse_args(list(argv))
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"import: {exc}", file=sys.stderr)
        return 2
    try:
        importer = BagImporter(config, progress=not args.no_progress)
    except SpoolError as exc:
        print(
            f"import: {exc}. The agent of robot {config.robot} seems to be running: imports and "
            "live capture share the robot's sequence numbers, so stop the agent first, or "
            "import with a robot of its own (another config).",
            file=sys.stderr,
        )
        return 2
    previous = {
        signum: signal.signal(signum, lambda *_: importer.stopping.set())
        for signum in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        reports = importer.run(args.files, upload_timeout=args.upload_timeout)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for line in summary_lines(reports, importer):
        print(line)
    refused_by_portal = importer.counters.failed - _conversion_failures(reports)
    if refused_by_portal or any(report.refused or report.stopped for report in reports):
        return 1
    return 3 if len(importer.spool) else 0
