"""The agent's path from a message to the portal, built once from the config: Recorder (seal
into the spool), Spool (on disk), Uploader (to the portal). The ROS 2 agent (ros_agent.ros2)
and the import of recordings (ros_agent.bags) use it as it is; the rospy node builds the same
three parts in node.Agent."""

import ipaddress
from dataclasses import dataclass
from urllib.parse import urlsplit

from ros_agent.config import AgentConfig
from ros_agent.counters import AgentCounters
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
    by another agent); `flush_interval` and `backoff_max` override the config's."""
    counters = AgentCounters()
    spool = Spool(config.spool_dir, max_bytes=config.spool_max_bytes)
    uploader = Uploader(
        spool=spool,
        client=PortalClient(
            records_url=config.records_url,
            token=config.token,
            tls_verify=config.tls_verify,
            timeout=config.request_timeout,
        ),
        counters=counters,
        batch_size=config.batch_size,
        batch_max_bytes=config.batch_max_bytes,
        flush_interval=config.flush_interval if flush_interval is None else flush_interval,
        backoff_max=config.backoff_max if backoff_max is None else backoff_max,
    )
    recorder = Recorder(
        spool=spool,
        key=config.key,
        owner=config.owner,
        robot=config.robot,
        counters=counters,
        on_spooled=uploader.notify,
    )
    return Pipeline(counters, spool, uploader, recorder)


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
