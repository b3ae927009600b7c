"""The parts of the AuthROS contract's interface the check uses (contracts/AuthROS.sol)."""

from eth_utils import keccak

ROOT_OF = {
    "inputs": [
        {"internalType": "address", "name": "sender", "type": "address"},
        {"internalType": "bytes32", "name": "root", "type": "bytes32"},
    ],
    "name": "rootOf",
    "outputs": [
        {"internalType": "uint64", "name": "size", "type": "uint64"},
        {"internalType": "uint64", "name": "time", "type": "uint64"},
        {"internalType": "uint64", "name": "blockNumber", "type": "uint64"},
    ],
    "stateMutability": "view",
    "type": "function",
}
DATA_QUERY = {
    "inputs": [
        {"internalType": "address", "name": "owner", "type": "address"},
        {"internalType": "bytes32", "name": "id", "type": "bytes32"},
    ],
    "name": "dataQueryOf",
    "outputs": [
        {"internalType": "address", "name": "recordOwner", "type": "address"},
        {"internalType": "bytes32", "name": "digest", "type": "bytes32"},
        {"internalType": "uint64", "name": "time", "type": "uint64"},
        {"internalType": "bytes32", "name": "dataType", "type": "bytes32"},
    ],
    "stateMutability": "view",
    "type": "function",
}
ROOT_ANCHORED = {
    "anonymous": False,
    "inputs": [
        {"indexed": True, "internalType": "address", "name": "sender", "type": "address"},
        {"indexed": True, "internalType": "bytes32", "name": "root", "type": "bytes32"},
        {"indexed": False, "internalType": "uint64", "name": "size", "type": "uint64"},
        {"indexed": False, "internalType": "bytes32", "name": "prevRoot", "type": "bytes32"},
        {"indexed": False, "internalType": "uint64", "name": "time", "type": "uint64"},
    ],
    "name": "RootAnchored",
    "type": "event",
}
DATA_UPLOADED = {
    "anonymous": False,
    "inputs": [
        {"indexed": True, "internalType": "bytes32", "name": "id", "type": "bytes32"},
        {"indexed": True, "internalType": "address", "name": "owner", "type": "address"},
        {"indexed": False, "internalType": "bytes32", "name": "digest", "type": "bytes32"},
        {"indexed": False, "internalType": "uint64", "name": "time", "type": "uint64"},
        {"indexed": False, "internalType": "bytes32", "name": "dataType", "type": "bytes32"},
    ],
    "name": "DataUploaded",
    "type": "event",
}
ROBOT_KEY_OF = {
    "inputs": [{"internalType": "bytes32", "name": "keyHash", "type": "bytes32"}],
    "name": "robotKeyOf",
    "outputs": [
        {"internalType": "address", "name": "owner", "type": "address"},
        {"internalType": "uint64", "name": "addedBlock", "type": "uint64"},
        {"internalType": "uint64", "name": "revokedBlock", "type": "uint64"},
    ],
    "stateMutability": "view",
    "type": "function",
}
ROBOT_KEY_OF_OWNER = {
    "inputs": [
        {"internalType": "address", "name": "owner", "type": "address"},
        {"internalType": "bytes32", "name": "keyHash", "type": "bytes32"},
    ],
    "name": "robotKeyOfOwner",
    "outputs": [
        {"internalType": "uint64", "name": "addedBlock", "type": "uint64"},
        {"internalType": "uint64", "name": "revokedBlock", "type": "uint64"},
    ],
    "stateMutability": "view",
    "type": "function",
}
ROBOT_KEY_ADDED = {
    "anonymous": False,
    "inputs": [
        {"indexed": True, "internalType": "address", "name": "owner", "type": "address"},
        {"indexed": True, "internalType": "bytes32", "name": "keyHash", "type": "bytes32"},
        {"indexed": False, "internalType": "bytes", "name": "publicKey", "type": "bytes"},
    ],
    "name": "RobotKeyAdded",
    "type": "event",
}
ROBOT_KEY_REVOKED = {
    "anonymous": False,
    "inputs": [
        {"indexed": True, "internalType": "address", "name": "owner", "type": "address"},
        {"indexed": True, "internalType": "bytes32", "name": "keyHash", "type": "bytes32"},
    ],
    "name": "RobotKeyRevoked",
    "type": "event",
}
ABI = [
    ROOT_OF,
    DATA_QUERY,
    ROBOT_KEY_OF,
    ROBOT_KEY_OF_OWNER,
    ROOT_ANCHORED,
    DATA_UPLOADED,
    ROBOT_KEY_ADDED,
    ROBOT_KEY_REVOKED,
]


def event_topic(event: dict) -> bytes:
    """topic[0] of an event's logs: keccak of its signature."""
    types = ",".join(item["type"] for item in event["inputs"])
    return keccak(text=f"{event['name']}({types})")
