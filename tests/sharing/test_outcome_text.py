"""An export's left-out list says why in words (the `outcome_text` filter), not as a code."""

import pytest
from django.template import Context, Template

pytestmark = pytest.mark.nodb


def test_an_outcome_code_reads_as_the_record_pages_words():
    template = Template("{% load verdicts %}{{ reason|outcome_text }}")
    assert template.render(Context({"reason": "not_anchored_yet"})) == "not anchored yet"
    assert template.render(Context({"reason": "signature_refused"})) == "signature not valid"
    assert template.render(Context({"reason": "something_new"})) == "something_new"
