"""Owner pages of the accounts app: registration, sign-in, key rotation, robots.

Views validate, call one service and answer; reads go through the selectors. Every page
but registration and sign-in needs a logged-in owner (`owner_required`). The dashboard,
which counts the owner's records and grants too, is the project's (portal/views.py).
"""

import math
from datetime import timedelta

from axes.helpers import get_cool_off
from django.conf import settings
from django.contrib import messages
from django.contrib.auth import login
from django.contrib.auth import views as auth_views
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import get_object_or_404, redirect, render
from django.urls import reverse_lazy
from django.utils import timezone
from django.utils.decorators import method_decorator
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET, require_http_methods, require_POST
from rest_framework.throttling import BaseThrottle

from accounts.agent_config import agent_config_yaml, config_filename, key_filename
from accounts.decorators import no_store, owner_required, page_throttle
from accounts.errors import (
    AccountError,
    InvalidKeyMaterial,
    InvalidOwnerToken,
    InvalidRobotName,
    InvalidUsername,
    KeyAlreadyUsed,
    RobotNameTaken,
    UsernameTaken,
    WeakPassword,
)
from accounts.forms import (
    ApiTokenCreateForm,
    KeyRotateForm,
    PairingAnswerForm,
    PairingCodeForm,
    RegisterForm,
    RobotCreateForm,
    RobotRetentionForm,
)
from accounts.keyexchange import portal_sm2_public_key
from accounts.models import ChainState, Owner, Robot
from accounts.selectors import (
    owner_for_user,
    owner_key_current,
    owner_keys,
    owner_token_list,
    pairing_code_display,
    public_key_fingerprint,
    robot_list_of,
    robot_pairing_pending,
    robot_pairings_answered,
    robot_topics,
)
from accounts.services.api_tokens import owner_token_create
from accounts.services.keys import key_rotate
from accounts.services.owners import owner_create
from accounts.services.pairing import robot_pairing_answer
from accounts.services.robots import robot_create, robot_retention_set, robot_token_revoke
from accounts.signup_limits import signup_slot_give_back, signup_slot_take

# The session backend that `login()` records for a user who has just registered.
MODEL_BACKEND = "django.contrib.auth.backends.ModelBackend"


# --- registration and sign-in ----------------------------------------------------------------


@never_cache
@require_http_methods(["GET", "POST"])
def register(request: HttpRequest) -> HttpResponse:
    if owner_for_user(request.user) is not None:
        return redirect("dashboard")
    form = RegisterForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        # Every owner costs the operator chain work: a registration counts against the
        # sign-up limits (accounts.signup_limits) before anything is created.
        slot = signup_slot_take(address=client_ip_address(request))
        if not slot.allowed:
            return _signup_throttled(request, slot.retry_after)
        try:
            owner = owner_create(
                username=form.cleaned_data["username"],
                password=form.cleaned_data["password1"],
                sm4_key=form.cleaned_data["key_ciphertext"],
                self_signup=True,
            )
        except (UsernameTaken, InvalidUsername) as exc:
            form.add_error("username", str(exc))
        except WeakPassword as exc:
            form.add_error("password1", exc.messages)
        except InvalidKeyMaterial as exc:
            form.add_error("key_ciphertext", str(exc))
        else:
            login(request, owner.user, backend=MODEL_BACKEND)
            return redirect("registration-progress")
        signup_slot_give_back(slot)  # refused: nothing was created
    status = 400 if form.is_bound else 200
    return render(
        request,
        "accounts/register.html",
        {"form": form, "sm2_public_key": portal_sm2_public_key()},
        status=status,
    )


def _signup_throttled(request: HttpRequest, retry_after: int) -> HttpResponse:
    """429: too many registrations from this address, or overall; nothing was created."""
    context = {"minutes": max(1, math.ceil(retry_after / 60))}
    response = render(request, "accounts/signup_throttled.html", context, status=429)
    response["Retry-After"] = str(retry_after)
    return response


@owner_required
@page_throttle()
@require_GET
def registration_progress(request: HttpRequest) -> HttpResponse:
    return render(
        request, "accounts/registration_progress.html", {"owner": request.owner, **_steps(request)}
    )


@owner_required
@page_throttle()
@require_GET
def account_status(request: HttpRequest) -> JsonResponse:
    """What the progress pages poll: the owner's and the current key's on-chain state."""
    owner: Owner = request.owner
    key = owner_key_current(owner)
    response = JsonResponse(
        {
            "username": owner.username,
            "eoa_address": owner.eoa_address,
            "chain_state": owner.chain_state,
            "fund_tx": owner.fund_tx,
            "enroll_tx": owner.enroll_tx,
            "register_tx": owner.register_tx,
            "registered_block": owner.registered_block,
            "chain_error": owner.chain_error,
            "key": {
                "key_id": key.key_id,
                "chain_state": key.chain_state,
                "tx_hash": key.tx_hash,
                "block_number": key.block_number,
            },
        }
    )
    return no_store(response)


def _steps(request: HttpRequest) -> dict[str, object]:
    owner: Owner = request.owner
    return {
        "confirmed": owner.chain_state == ChainState.CONFIRMED,
        "failed": owner.chain_state == ChainState.FAILED,
        "steps": [
            ("fund", "EOA funded by the portal operator", owner.fund_tx),
            ("enroll", "EOA enrolled in the AuthROS contract", owner.enroll_tx),
            ("register", "Key commitment registered", owner.register_tx),
        ],
    }


class LoginView(auth_views.LoginView):
    """Django's login, with django-axes' lockout shown as a page of its own (429)."""

    template_name = "accounts/login.html"
    redirect_authenticated_user = True

    def form_invalid(self, form: object) -> HttpResponse:
        if getattr(self.request, "axes_locked_out", False):
            cool_off = get_cool_off(self.request)
            minutes = max(1, round(cool_off.total_seconds() / 60)) if cool_off else None
            # Our page replaces the plain-text one django-axes' middleware would send.
            self.request.axes_locked_out = False
            return render(
                self.request,
                "accounts/locked_out.html",
                {"minutes": minutes, "failure_limit": settings.AXES_FAILURE_LIMIT},
                status=429,
            )
        response = super().form_invalid(form)
        response.status_code = 400
        return response


def client_ip_address(request: HttpRequest) -> str | None:
    """The address django-axes counts failed sign-ins against (AXES_CLIENT_IP_CALLABLE).

    The API throttles' rule, so both honour API_NUM_PROXIES: with 0 the peer address, else
    the X-Forwarded-For entry that many proxies from the right, the one our proxy appended.
    """
    return BaseThrottle().get_ident(request)


@method_decorator(owner_required, name="dispatch")
@method_decorator(page_throttle(), name="dispatch")
class PasswordChangeView(auth_views.PasswordChangeView):
    """An owner's password; operators change theirs in the admin console."""

    template_name = "accounts/password_change.html"
    success_url = reverse_lazy("dashboard")

    def form_valid(self, form: object) -> HttpResponse:
        messages.success(self.request, "Your password was changed.")
        return super().form_valid(form)


# --- key ------------------------------------------------------------------------------------


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def key_rotation(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = KeyRotateForm(request.POST or None, user=request.user)
    if request.method == "POST" and form.is_valid():
        try:
            new_key = key_rotate(owner=owner, sm4_key=form.cleaned_data["key_ciphertext"])
        except (InvalidKeyMaterial, KeyAlreadyUsed) as exc:
            form.add_error("key_ciphertext", str(exc))
        else:
            messages.success(
                request,
                f"Your new key {new_key.key_id} is in use. Paired robots fetch it by themselves "
                "on their next contact, and what they spooled under the old key still arrives. "
                "Robots whose key file you set by hand need the new key within the hour.",
            )
            return redirect("key-rotation")
    keys = owner_keys(owner)
    context = {
        "form": form,
        "owner": owner,
        "keys": keys,
        "pending": any(key.chain_state == ChainState.PENDING for key in keys),
        "sm2_public_key": portal_sm2_public_key(),
    }
    return render(request, "accounts/key.html", context, status=400 if form.is_bound else 200)


# --- robots --------------------------------------------------------------------------------


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def robots(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = RobotCreateForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            robot, token = robot_create(
                owner=owner, name=form.cleaned_data["name"], topics=form.cleaned_data["topics"]
            )
        except (RobotNameTaken, InvalidUsername) as exc:
            form.add_error("name", str(exc))
        else:
            config = _agent_config(request, robot, token=token)
            context = {
                "robot": robot,
                "token": token,
                "config": config,
                "config_filename": config_filename(robot.name),
                "key_filename": key_filename(owner.username),
            }
            # The token exists only in this response: it is never stored nor shown again.
            return no_store(render(request, "accounts/robot_created.html", context, status=201))
    return _robots_page(request, form=form, status=400 if form.is_bound else 200)


def _robots_page(
    request: HttpRequest,
    *,
    form: RobotCreateForm | None = None,
    code_form: PairingCodeForm | None = None,
    pairing: object = None,
    answer_form: PairingAnswerForm | None = None,
    status: int = 200,
) -> HttpResponse:
    owner: Owner = request.owner
    context = {
        "form": form or RobotCreateForm(),
        "code_form": code_form or PairingCodeForm(),
        "pairing": pairing,
        "answer_form": answer_form,
        "robots": robot_list_of(owner),
        "answered": [
            {"pairing": p, "code": pairing_code_display(p.code)}
            for p in robot_pairings_answered(owner)
        ],
    }
    if pairing is not None:
        context["pairing_code"] = pairing_code_display(pairing.code)
        context["pairing_fingerprint"] = public_key_fingerprint(pairing.public_key)
    return render(request, "accounts/robots.html", context, status=status)


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def robot_pair(request: HttpRequest) -> HttpResponse:
    """GET ?code=: the pairing request a robot printed the code of, to approve or refuse;
    POST: the owner's answer (robot_pairing_answer)."""
    if request.method == "GET":
        code_form = PairingCodeForm(request.GET)
        if not code_form.is_valid():
            return _robots_page(request, code_form=code_form, status=400)
        pairing = robot_pairing_pending(code=code_form.cleaned_data["code"])
        if pairing is None:
            code_form.add_error(
                "code",
                "No robot waits for an answer with this code: check what the robot printed "
                "(a request expires after a while; run its pair command again).",
            )
            return _robots_page(request, code_form=code_form, status=404)
        answer_form = PairingAnswerForm(initial={"code": pairing.code, "name": pairing.name})
        return _robots_page(request, code_form=code_form, pairing=pairing, answer_form=answer_form)
    answer_form = PairingAnswerForm(request.POST)
    if not answer_form.is_valid():
        return _robots_page(request, status=400)
    data = answer_form.cleaned_data
    approve = data["decision"] == "approve"
    try:
        pairing = robot_pairing_answer(
            owner=request.owner,
            code=data["code"],
            approve=approve,
            actor=request.user,
            name=data["name"].strip() or None,
        )
    except (RobotNameTaken, InvalidRobotName) as exc:
        again = robot_pairing_pending(code=data["code"])
        answer_form.add_error("name", str(exc))
        return _robots_page(request, pairing=again, answer_form=answer_form, status=400)
    except AccountError as exc:
        messages.error(request, str(exc))
        return _robots_page(request, status=exc.http_status)
    if approve:
        messages.success(
            request,
            f"{pairing.robot.name} is paired: it receives its token and your key, encrypted to "
            "its own SM2 key, and starts uploading.",
        )
    else:
        messages.info(request, f"The request {pairing_code_display(pairing.code)} is refused.")
    return redirect("robots")


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def robot_revoke(request: HttpRequest, robot_id: str) -> HttpResponse:
    """GET: what revoking (unpairing) the robot does, to confirm; POST: revoke its token."""
    robot = get_object_or_404(Robot, pk=robot_id, owner=request.owner)
    if request.method == "GET":
        return render(request, "accounts/robot_revoke.html", {"robot": robot})
    if robot.is_active:
        robot_token_revoke(robot=robot, actor=request.user)
        messages.success(
            request,
            f"The token of {robot.name} is revoked: its uploads now fail, and it gets no "
            "key any more.",
        )
    else:
        messages.info(request, f"The token of {robot.name} was already revoked.")
    return redirect("robots")


@owner_required
@page_throttle()
@require_POST
def robot_retention(request: HttpRequest, robot_id: str) -> HttpResponse:
    """Set how many days the robot's records are kept (empty: forever)."""
    robot = get_object_or_404(Robot, pk=robot_id, owner=request.owner)
    form = RobotRetentionForm(request.POST)
    if not form.is_valid():
        errors = "; ".join(form.errors.get("retention_days", ["not a number of days"]))
        messages.error(request, f"Retention of {robot.name} unchanged: {errors}")
        return redirect("robots")
    days = form.cleaned_data["retention_days"]
    robot_retention_set(robot=robot, days=days, actor=request.user)
    if days is None:
        messages.success(request, f"The records of {robot.name} are kept until you delete them.")
    else:
        messages.success(
            request,
            f"The records of {robot.name} are kept {days} day{'s' if days != 1 else ''} after "
            "capture; older ones are deleted within the hour (once anchored).",
        )
    return redirect("robots")


@owner_required
@page_throttle()
@require_GET
def robot_config(request: HttpRequest, robot_id: str) -> HttpResponse:
    """The agent config again, without the token (shown once): it names a token file."""
    robot = get_object_or_404(Robot, pk=robot_id, owner=request.owner)
    text = _agent_config(request, robot, token=None)
    response = HttpResponse(text, content_type="application/yaml; charset=utf-8")
    response["Content-Disposition"] = f'attachment; filename="{config_filename(robot.name)}"'
    return no_store(response)


def _agent_config(request: HttpRequest, robot: Robot, *, token: str | None) -> str:
    """The robot's agent.yaml, pointing the agent at the address this page was asked at."""
    return agent_config_yaml(
        portal_url=request.build_absolute_uri("/"),
        robot_id=str(robot.id),
        robot_name=robot.name,
        owner_username=robot.owner.username,
        topics=robot_topics(robot),
        token=token,
        made_at=timezone.now(),
    )


# --- owner API tokens ------------------------------------------------------------------------
# Revoking one is sharing.views.tokens.api_token_revoke: it offers to take back the grants it made.


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def api_tokens(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = ApiTokenCreateForm(request.POST or None, user=request.user)
    if request.method == "POST" and form.is_valid():
        try:
            token, key = owner_token_create(
                owner=owner,
                name=form.cleaned_data["name"],
                scopes=form.cleaned_data["scopes"],
                expires_in=timedelta(days=form.cleaned_data["expires_in_days"]),
            )
        except InvalidOwnerToken as exc:
            form.add_error(None, str(exc))
        else:
            # The key exists only in this response: it is never stored nor shown again.
            context = {"token": token, "key": key}
            return no_store(render(request, "accounts/api_token_created.html", context, status=201))
    context = {"form": form, "tokens": owner_token_list(owner), "now": timezone.now()}
    return render(
        request, "accounts/api_tokens.html", context, status=400 if form.is_bound else 200
    )
