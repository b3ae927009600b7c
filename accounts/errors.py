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
