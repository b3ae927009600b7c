"""One input of a record selection in the API (sharing.apis.fields.RecordSelectionSerializer):
a grant's terms, an export and an export's count take robots, topics and a window by the same
fields, within RecordSelection's bounds, each with its own words."""

import dataclasses
import uuid

import pytest

from sharing.apis.exports import ExportSelectionSerializer
from sharing.apis.fields import SELECTION_FIELDS, RecordSelectionSerializer
from sharing.apis.grants import GrantsApi, GrantTermsInputSerializer
from sharing.selection import MAX_SELECTED_ROBOTS, MAX_SELECTED_TOPICS, RecordSelection

pytestmark = pytest.mark.nodb

INPUTS = [GrantTermsInputSerializer, GrantsApi.InputSerializer, ExportSelectionSerializer]


def test_the_selection_fields_are_recordselections_own():
    assert tuple(f.name for f in dataclasses.fields(RecordSelection)) == SELECTION_FIELDS
    assert SELECTION_FIELDS == ("robots", "topics", "since", "until")


@pytest.mark.parametrize("serializer", INPUTS)
def test_every_selecting_request_uses_the_one_selection_input(serializer):
    assert issubclass(serializer, RecordSelectionSerializer)
    fields = serializer().fields
    assert list(fields)[:4] == list(SELECTION_FIELDS)
    assert fields["robots"].max_length == MAX_SELECTED_ROBOTS
    assert fields["topics"].max_length == MAX_SELECTED_TOPICS
    assert all(fields[name].help_text for name in SELECTION_FIELDS)


def test_a_grant_may_send_a_null_window_end_an_export_may_not():
    robot = uuid.uuid4()
    grant = GrantTermsInputSerializer(data={"robots": [str(robot)], "since": None})
    assert grant.is_valid(), grant.errors
    assert grant.selection() == {"robots": [robot], "topics": (), "since": None, "until": None}
    export = ExportSelectionSerializer(data={"since": None})
    assert not export.is_valid()
    assert list(export.errors) == ["since"]


def test_nothing_given_selects_everything():
    export = ExportSelectionSerializer(data={})
    assert export.is_valid()
    assert export.selection() == {"robots": (), "topics": (), "since": None, "until": None}
