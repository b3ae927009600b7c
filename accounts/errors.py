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
