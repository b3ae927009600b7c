"""What a robot key dispute (accounts.services.robot_keys.RobotKeyDispute, issue 46) leaves: a
SecurityEvent for the operator, on the security page of the owner whose robot's key it is,
and, when that owner has the robot in this portal, the owner's `robot_key_disputed` alert.
Registered as the dispute listener in sharing/apps.py."""

import logging

from django.db import transaction

from accounts.services.robot_keys import RobotKeyDispute
from alerts.services import robot_key_disputed_alert
from sharing.models import SecurityEvent

security_log = logging.getLogger("authros.security")


def robot_key_dispute_record(dispute: RobotKeyDispute) -> None:
    robot = dispute.robot
    detail: dict[str, object] = {
        "where": dispute.where,
        "key_hash": dispute.key_hash,
        "claimed_by": dispute.claimant_eoa,
    }
    if robot is not None:
        detail.update(robot=str(robot.pk), name=robot.name)
    with transaction.atomic():
        SecurityEvent.objects.create(
            kind=SecurityEvent.Kind.ROBOT_KEY_DISPUTED, owner=dispute.owner, detail=detail
        )
        if robot is not None:
            robot_key_disputed_alert(
                owner=dispute.owner,
                robot_id=robot.pk,
                robot=robot.name,
                key_hash=dispute.key_hash,
                claimant_eoa=dispute.claimant_eoa,
                where=dispute.where,
            )
    security_log.warning("robot key %s disputed (%s): %s", dispute.key_hash, dispute.where, detail)
