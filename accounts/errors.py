"""What the accounts services refuse, as values the caller can act on."""

from core.errors import DomainError


class AccountError(DomainError):
    """Base: `code` is the machine-readable error, the message says what to do."""

    code = "account_error"
    http_status = 400


class UsernameTaken(AccountError):
    code = "username_taken"


class InvalidUsername(AccountError):
    code = "invalid_username"


class WeakPassword(AccountError):
    code = "weak_password"

    def __init__(self, messages: list[str]) -> None:
        self.messages = messages
        super().__init__(" ".join(messages))


class InvalidKeyMaterial(AccountError):
    code = "invalid_key"


class KeyAlreadyUsed(AccountError):
    code = "key_already_used"


class InvalidRobotName(AccountError):
    code = "invalid_robot_name"


class RobotNameTaken(AccountError):
    code = "robot_name_taken"


class InvalidOwnerToken(AccountError):
    """An API token asked for with a bad name, scopes or lifetime."""

    code = "invalid_api_token"


class InsufficientScope(AccountError):
    """An owner API token used for what its scopes do not cover."""

    code = "insufficient_scope"
    http_status = 403


class MasterKeyRefused(AccountError):
    """The master key (KEK) is missing while owner keys are wrapped under it, or is not the one
    they were wrapped under: nothing is wrapped or served until an operator restores it."""

    code = "service_misconfigured"
    http_status = 503


class IdentityMismatch(AccountError):
    """The key commitment on chain is not the one of the key the portal holds for the owner."""

    code = "identity_check_failed"
    http_status = 409


# --- robot pairing ----------------------------------------------------------------------------


class InvalidPairingRequest(AccountError):
    """A pairing request with a bad name or an SM2 public key that is no point on sm2p256v1."""

    code = "invalid_pairing_request"


class PairingNotFound(AccountError):
    """No pairing request with this code or id waits for an answer (mistyped, or expired)."""

    code = "pairing_not_found"
    http_status = 404


class PairingExpired(AccountError):
    code = "pairing_expired"
    http_status = 409


class PairingAlreadyAnswered(AccountError):
    """The request was approved or refused already: a second answer is refused."""

    code = "pairing_already_answered"
    http_status = 409


class PairingAlreadyCollected(AccountError):
    """The token and key of an approved request are handed out once; this was the second ask."""

    code = "pairing_already_collected"
    http_status = 409


class PairingRefused(AccountError):
    """The owner refused the request (or unpaired the robot before it collected): nothing."""

    code = "pairing_refused"
    http_status = 403


class PairingSecretMismatch(AccountError):
    """Someone without the robot's request secret asked for its answer."""

    code = "pairing_secret_mismatch"
    http_status = 403


class RobotKeyTaken(AccountError):
    """A pairing request names a key another owner's robot has (in the portal, or first on
    chain): a key is its registering owner's, so the approval is refused (issue 46)."""

    code = "robot_key_taken"
    http_status = 409


class RobotNotPaired(AccountError):
    """A robot added by hand has no SM2 key to send its owner's key to: pair it instead."""

    code = "robot_not_paired"
    http_status = 409


class WrongPassword(AccountError):
    """A sensitive action (deleting the account) confirmed with another password than the
    owner's."""

    code = "wrong_password"
    http_status = 403


class InvalidRetention(AccountError):
    code = "invalid_retention"
