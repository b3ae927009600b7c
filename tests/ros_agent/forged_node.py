"""A forged ROS node for the tests: it listens on a robot's topic and uploads in its name.

    python -m tests.ros_agent.forged_node --mode MODE --portal URL --token T --owner O
        --robot R --topic /chatter --answers answers.jsonl [--key-file F]

It subscribes through the real ROS master, so it hears exactly what the robot's own agent
hears, wraps each std_msgs/String message as the agent does (the Fig. 4 record, envelope v1),
and POSTs it to the portal's records endpoint. What is forged depends on MODE:

    no_key       it has no key: it uploads the record unencrypted, as a bare "envelope"
    wrong_key    it seals with a key of its own, not the owner's
    stale_seq    it has the owner's key (stolen) but reuses sequence number 1
    other_token  it has the owner's key but authenticates with another robot's token

Every answer is appended to --answers as one JSON line {"status", "error"}.
"""

import argparse
import base64
import json
import threading
from datetime import UTC, datetime
from pathlib import Path

import requests
import rospy
from std_msgs.msg import String

from ros_agent.wrapping import envelope_header, record_json
from smcrypto import envelope, sm4

MODES = ("no_key", "wrong_key", "stale_seq", "other_token")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", choices=MODES, required=True)
    parser.add_argument("--portal", required=True)
    parser.add_argument("--token", required=True)
    parser.add_argument("--owner", required=True)
    parser.add_argument("--robot", required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--answers", required=True)
    parser.add_argument("--key-file")
    args = parser.parse_args()
    if args.mode == "wrong_key":
        key = sm4.generate_key()
    elif args.key_file:
        key = bytes.fromhex(Path(args.key_file).read_text().strip())
    else:
        key = None
    session = requests.Session()
    session.headers["Authorization"] = f"Token {args.token}"
    lock = threading.Lock()
    seq = iter(range(time_seq(), 2**62))

    def forge(msg: String) -> None:
        now = datetime.now(UTC)
        plaintext = record_json(
            data={"data": msg.data},
            owner=args.owner,
            topic=args.topic,
            ros_type="std_msgs/String",
            captured_at=now,
        )
        with lock:
            if args.mode == "no_key":
                data = plaintext
            else:
                number = 1 if args.mode == "stale_seq" else next(seq)
                header = envelope_header(
                    owner=args.owner,
                    robot=args.robot,
                    topic=args.topic,
                    ros_type="std_msgs/String",
                    seq=number,
                    captured_at=now,
                )
                data = envelope.seal(key, header, plaintext)
            answer = session.post(
                f"{args.portal.rstrip('/')}/api/v1/records/",
                json={"envelope": base64.b64encode(data).decode()},
                timeout=30,
            )
            body = (
                answer.json()
                if answer.headers.get("Content-Type", "").startswith("application/json")
                else {}
            )
            with Path(args.answers).open("a") as log:
                log.write(json.dumps({"status": answer.status_code, "error": body.get("error")}))
                log.write("\n")

    rospy.init_node(f"forged_{args.mode}", anonymous=True, disable_signals=False)
    rospy.Subscriber(args.topic, String, forge, queue_size=10)
    rospy.spin()


def time_seq() -> int:
    """A sequence number above any the real agent has used so far (it counts microseconds)."""
    return int(datetime.now(UTC).timestamp() * 1_000_000) + 1_000_000_000


if __name__ == "__main__":
    main()
