"""The agent's path from a message to the portal, built once from the config: Recorder (seal
into the spool), Spool (on disk), Uploader (to the portal; for a paired robot each batch is
signed once, and its records numbered, before it leaves: ros_agent.batches).
The rospy node (ros_agent.node), the ROS 2 agent (ros_agent.ros2) and the import of
recordings (ros_agent.bags) all use it as it is."""

import ipaddress
from dataclasses import dataclass
from urllib.parse import urlsplit

from ros_agent.config import AgentConfig
from ros_agent.counters import AgentCounters
from ros_agent.keyring import Keyring
from ros_agent.pairing import KeyUpdater
from ros_agent.sealing import robot_signing_key
from ros_agent.spool import Spool
from ros_agent.uploader import PortalClient, Uploader
from ros_agent.wrapping import Recorder


@dataclass
class Pipeline:
    counters: AgentCounters
    spool: Spool
    uploader: Uploader
    recorder: Recorder

    def stats(self) -> dict[str, int]:
        """The counters, plus what waits in the spool."""
        return {
            **self.counters.snapshot(),
            "queued": len(self.spool),
            "spool_bytes": self.spool.used_bytes,
        }


def pipeline_build(
    config: AgentConfig, *, flush_interval: float | None = None, backoff_max: float | None = None
) -> Pipeline:
    """Spool, Uploader and Recorder for the robot of `config` (SpoolError if the spool is held
    by another agent, or its record counters are unreadable); `flush_interval` and
    `backoff_max` override the config's."""
    counters = AgentCounters()
    spool = Spool(config.spool_dir, max_bytes=config.spool_max_bytes)
    client = PortalClient(
        records_url=config.records_url,
        robot_key_url=config.robot_key_url,
        token=config.token,
        tls_verify=config.tls_verify,
        timeout=config.request_timeout,
    )
    keyring, key_updater = key_parts(config, client)
    try:
        uploader = Uploader(
            spool=spool,
            client=client,
            keyring=keyring if key_updater else None,
            key_updater=key_updater,
            counters=counters,
            batch_size=config.batch_size,
            batch_max_bytes=config.batch_max_bytes,
            flush_interval=config.flush_interval if flush_interval is None else flush_interval,
            backoff_max=config.backoff_max if backoff_max is None else backoff_max,
            signing_key=robot_signing_key(config),
        )
    except BaseException:
        spool.close()
        raise
    recorder = Recorder(
        spool=spool,
        keyring=keyring,
        owner=config.owner,
        robot=config.robot,
        counters=counters,
        on_spooled=uploader.notify,
    )
    return Pipeline(counters, spool, uploader, recorder)


def key_parts(config: AgentConfig, client: PortalClient) -> tuple[Keyring, KeyUpdater | None]:
    """The owner's keys the robot seals under, and for a paired robot (ros_agent.pairing) what
    fetches a rotated key into them; None for a robot whose key file is set by hand."""
    keyring = config.keyring or Keyring.of_one(config.key)
    if not config.paired:
        return keyring, None
    updater = KeyUpdater(client=client, keyring=keyring, sm2_private_key=config.sm2_private_key)
    return keyring, updater


def token_in_clear(portal_url: str) -> str | None:
    """The host the robot token travels to in clear (plain http, not loopback), or None."""
    parts = urlsplit(portal_url)
    if parts.scheme != "http":
        return None
    host = parts.hostname or ""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    return None if loopback else host


CLEAR_TEXT_WARNING = (
    "portal_url is plain http to %s: envelopes are sealed, but the robot token travels in "
    "clear; use https"
)
