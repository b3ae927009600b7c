"""sm2p256v1 (GB/T 32918.5) and the parts of GB/T 32918.2/.4 every SM2 backend computes alike:
the curve check, the signer's Z and digest e, and the key derivation function. Python ints and
the project's SM3; nothing here touches a secret scalar."""

from smcrypto.sm3 import DIGEST_SIZE, sm3_digest

P = 0xFFFFFFFEFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFF00000000FFFFFFFFFFFFFFFF
A = 0xFFFFFFFEFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFFF00000000FFFFFFFFFFFFFFFC
B = 0x28E9FA9E9D9F5E344D5A9E4BCF6509A7F39789F515AB8F92DDBCBD414D940E93
N = 0xFFFFFFFEFFFFFFFFFFFFFFFFFFFFFFFF7203DF6B21C6052B53BBF40939D54123
G_X = 0x32C4AE2C1F1981195F9904466A39C9948FE30BBFF2660BE1715A4589334C74C7
G_Y = 0xBC3736A2F4F6779C59BDCEE36B692153D0A9877CC62A474002DF32E52139F0A0
COORDINATE_SIZE = 32
POINT_SIZE = 2 * COORDINATE_SIZE
C2_OFFSET = POINT_SIZE + DIGEST_SIZE
# GB/T 32918.2's default user ID, as gmssl, Tongsuo and sm-crypto use it; ENTL is its bit length
DEFAULT_ID = b"1234567812345678"
_Z_PREFIX = (
    (8 * len(DEFAULT_ID)).to_bytes(2, "big")
    + DEFAULT_ID
    + b"".join(value.to_bytes(COORDINATE_SIZE, "big") for value in (A, B, G_X, G_Y))
)


def on_curve(point: bytes) -> bool:
    """Whether x||y (64 bytes) is a point of sm2p256v1 (the curve has cofactor 1, so every
    such point is of order n)."""
    x = int.from_bytes(point[:COORDINATE_SIZE], "big")
    y = int.from_bytes(point[COORDINATE_SIZE:], "big")
    if x >= P or y >= P:
        return False
    return (y * y - (x * x * x + A * x + B)) % P == 0


def digest_e(public_key_xy: str, data: bytes) -> int:
    """e = SM3(Z || data) as an integer, Z = SM3(ENTL || ID || a || b || xG || yG || xA || yA)
    with the default ID (GB/T 32918.2, 6.1 and A.1)."""
    z = sm3_digest(_Z_PREFIX + bytes.fromhex(public_key_xy))
    return int.from_bytes(sm3_digest(z + data), "big")


def kdf(shared: bytes, length: int) -> bytes:
    """GB/T 32918.4's KDF over SM3: `length` bytes of SM3(shared || ct) for ct = 1, 2, ..."""
    blocks = -(-length // DIGEST_SIZE)
    stream = b"".join(sm3_digest(shared + ct.to_bytes(4, "big")) for ct in range(1, blocks + 1))
    return stream[:length]


def xor(data: bytes, stream: bytes) -> bytes:
    """data ^ stream, byte by byte (both of one length)."""
    value = int.from_bytes(data, "big") ^ int.from_bytes(stream, "big")
    return value.to_bytes(len(data), "big")
