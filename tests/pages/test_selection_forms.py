"""One input of a record selection on the pages (sharing.forms.RecordSelectionForm): the grant,
export and deletion forms pick robots, topics and a window by the same mixin and give the
services the same values."""

import uuid
from types import SimpleNamespace

import pytest

from sharing.forms import ExportForm, GrantForm, RecordDeleteSelectionForm, RecordSelectionForm


@pytest.mark.parametrize("form", [GrantForm, ExportForm, RecordDeleteSelectionForm])
def test_every_selecting_form_uses_the_one_mixin(form):
    assert issubclass(form, RecordSelectionForm)


@pytest.mark.nodb
def test_a_grant_and_an_export_give_several_robots_and_topics():
    owner = SimpleNamespace(username="alice")
    robots = [SimpleNamespace(pk=uuid.uuid4(), name=f"r{i}", owner=owner) for i in range(2)]
    data = {"grantee": "bob", "robots": [str(robots[1].pk)], "topics": ["/a"]}
    grant = GrantForm(data, robots=robots, topics=["/a", "/b"])
    export = ExportForm(data, robots=robots, topics=["/a", "/b"])
    for form in (grant, export):
        assert form.is_valid(), form.errors
        assert form.selection() == {
            "robots": [str(robots[1].pk)],
            "topics": ["/a"],
            "since": None,
            "until": None,
        }
    assert grant.fields["robots"].help_text.startswith("None ticked")
    assert export.fields["robots"].label == "Robots (none ticked: all)"


@pytest.mark.django_db
def test_a_deletion_gives_one_robot_and_one_topic(make_robot, upload):
    alice = make_robot("alice")
    record_topic = upload(alice, 1).topic
    form = RecordDeleteSelectionForm(
        {"robot": str(alice.robot.pk), "topic": record_topic}, owner=alice.owner
    )
    assert list(form.fields) == ["robot", "topic", "since", "until"]
    assert form.is_valid(), form.errors
    assert form.selection() == {
        "robot": str(alice.robot.pk),
        "topic": record_topic,
        "since": None,
        "until": None,
    }
