"""Forms of the owner pages: registration, key rotation, robots.

An SM4 key never reaches the server in plaintext: the page's script encrypts it to the
portal's SM2 public key and only the ciphertext is submitted (`key_ciphertext`).
"""

from django import forms
from django.contrib.auth import get_user_model
from django.contrib.auth.password_validation import (
    password_validators_help_text_html,
    validate_password,
)
from django.core.exceptions import ValidationError

from accounts.agent_config import DEFAULT_TOPICS, Topic
from accounts.errors import InvalidKeyMaterial, InvalidUsername
from accounts.keyexchange import sm4_key_from_submission
from accounts.models import RETENTION_MAX_DAYS, Owner, OwnerToken, validate_robot_topics
from accounts.usernames import username_check, username_skeleton

NO_SCRIPT_KEY = (
    "Your key was not encrypted in the browser, so it was not sent. This page needs "
    "JavaScript to encrypt the key before it leaves your computer: enable it and try again."
)


class EncryptedKeyField(forms.CharField):
    """The SM4 key as SM2 ciphertext (C1C3C2 hex); cleans to the 16 key bytes."""

    widget = forms.HiddenInput

    def __init__(self, **kwargs: object) -> None:
        super().__init__(required=False, max_length=1024, strip=True, **kwargs)

    def clean(self, value: object) -> bytes:
        text = super().clean(value)
        if not text:
            raise ValidationError(NO_SCRIPT_KEY, code="key_not_encrypted")
        try:
            return sm4_key_from_submission(text)
        except InvalidKeyMaterial as exc:
            raise ValidationError(str(exc), code="invalid_key") from None


class RegisterForm(forms.Form):
    username = forms.CharField(
        max_length=150,
        help_text="Up to 150 characters: ASCII letters, digits and @ . + - _ only. A name "
        "that looks like a taken one (Alice beside alice, a1ice) is taken too.",
        widget=forms.TextInput(attrs={"autocomplete": "username", "autofocus": True}),
    )
    password1 = forms.CharField(
        label="Password",
        strip=False,
        widget=forms.PasswordInput(attrs={"autocomplete": "new-password"}),
        help_text=password_validators_help_text_html(),
    )
    password2 = forms.CharField(
        label="Password again",
        strip=False,
        widget=forms.PasswordInput(attrs={"autocomplete": "new-password"}),
    )
    key_ciphertext = EncryptedKeyField()

    def clean_username(self) -> str:
        username = self.cleaned_data["username"]
        try:
            username_check(username)
        except InvalidUsername as exc:
            text = str(exc)
            raise ValidationError(
                f"{text[:1].upper()}{text[1:]}.", code="invalid_username"
            ) from None
        taken = get_user_model().objects.filter(username=username).exists()
        if taken or Owner.objects.filter(name_skeleton=username_skeleton(username)).exists():
            raise ValidationError(
                "This username is taken, or looks like one that is.", code="username_taken"
            )
        return username

    def clean(self) -> dict:
        cleaned = super().clean()
        password1, password2 = cleaned.get("password1"), cleaned.get("password2")
        if password1 and password2 and password1 != password2:
            self.add_error("password2", "The two passwords differ.")
        elif password1:
            candidate = get_user_model()(username=cleaned.get("username", ""))
            try:
                validate_password(password1, candidate)
            except ValidationError as exc:
                self.add_error("password1", exc)
        return cleaned


class PasswordConfirmedForm(forms.Form):
    """A sensitive change confirmed with the owner's password (`password`), checked against
    `user`; subclasses say why in `why_confirm`."""

    password = forms.CharField(
        label="Your password",
        strip=False,
        widget=forms.PasswordInput(attrs={"autocomplete": "current-password"}),
    )
    why_confirm = "Confirm it is you."

    def __init__(self, *args: object, user: object, **kwargs: object) -> None:
        self.user = user
        super().__init__(*args, **kwargs)
        self.fields["password"].help_text = self.why_confirm

    def clean_password(self) -> str:
        password = self.cleaned_data["password"]
        if not self.user.check_password(password):
            raise ValidationError("This is not your password.", code="wrong_password")
        return password


class KeyRotateForm(PasswordConfirmedForm):
    why_confirm = "Rotating the key is a sensitive change: confirm it is you."

    key_ciphertext = EncryptedKeyField()


class RobotCreateForm(forms.Form):
    name = forms.CharField(
        max_length=100,
        help_text="A name you recognise, unique among your robots (e.g. turtlebot-3).",
    )
    topics = forms.CharField(
        widget=forms.Textarea(attrs={"rows": 3, "spellcheck": "false"}),
        initial="\n".join(f"{topic.name} {topic.type}" for topic in DEFAULT_TOPICS),
        help_text=(
            "What the robot's agent records, kept with the robot for its config file: one topic "
            "per line, its name then its ROS type, e.g. /robot/odom nav_msgs/Odometry."
        ),
    )

    def clean_name(self) -> str:
        name = self.cleaned_data["name"].strip()
        if not name:
            raise ValidationError("Give the robot a name.", code="required")
        return name

    def clean_topics(self) -> list[Topic]:
        entries = []
        for number, line in enumerate(self.cleaned_data["topics"].splitlines(), start=1):
            parts = line.split()
            if not parts:
                continue
            if len(parts) != 2:
                raise ValidationError(
                    f"Line {number}: write the topic name and its type, separated by a space.",
                    code="invalid_topic",
                )
            entries.append({"name": parts[0], "type": parts[1]})
        validate_robot_topics(entries)
        return [Topic(name=entry["name"], type=entry["type"]) for entry in entries]


# The lifetimes an owner picks from for an API token, in days.
API_TOKEN_LIFETIMES = (7, 30, 90, 365)


class ApiTokenCreateForm(PasswordConfirmedForm):
    """An owner API token: its name, scopes and lifetime, confirmed with the owner's password
    (a stolen session cookie must not mint a long-lived credential)."""

    name = forms.CharField(
        max_length=100,
        help_text="What will use it, e.g. nightly-export; shown in the list and on grants.",
    )
    scopes = forms.MultipleChoiceField(
        choices=OwnerToken.Scope.choices,
        widget=forms.CheckboxSelectMultiple,
        help_text="Give it only what the script needs.",
    )
    expires_in_days = forms.TypedChoiceField(
        label="Expires after",
        choices=[(days, f"{days} days") for days in API_TOKEN_LIFETIMES],
        coerce=int,
        initial=30,
    )
    why_confirm = "An API token acts for you until it expires: confirm it is you."
    field_order = ("name", "scopes", "expires_in_days", "password")

    def clean_name(self) -> str:
        name = self.cleaned_data["name"].strip()
        if not name:
            raise ValidationError("Give the token a name.", code="required")
        return name


class PairingCodeForm(forms.Form):
    """The code a robot printed (`python -m ros_agent pair`), typed by its owner."""

    code = forms.CharField(
        max_length=20,
        label="Pairing code",
        help_text="The code the robot printed, e.g. 7KQ2-M9XD.",
        widget=forms.TextInput(
            attrs={"autocomplete": "off", "spellcheck": "false", "autocapitalize": "characters"}
        ),
    )


class PairingAnswerForm(forms.Form):
    """The owner's answer to a pairing request: approve (under a name) or refuse."""

    code = forms.CharField(max_length=20, widget=forms.HiddenInput)
    name = forms.CharField(
        max_length=100,
        required=False,
        help_text="The robot's name in the portal (default: the name it asked with).",
    )
    decision = forms.ChoiceField(choices=[("approve", "approve"), ("refuse", "refuse")])

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("auto_id", "answer_%s")  # beside the code form on the same page
        super().__init__(*args, **kwargs)


class RobotRetentionForm(forms.Form):
    """How long a robot's records are kept; empty: until deleted by hand."""

    retention_days = forms.IntegerField(
        label="Keep records (days)",
        required=False,
        min_value=1,
        max_value=RETENTION_MAX_DAYS,
        help_text="Records captured longer ago are deleted, hourly. Empty: kept forever.",
        widget=forms.NumberInput(attrs={"inputmode": "numeric", "placeholder": "forever"}),
    )
