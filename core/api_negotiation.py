"""Content negotiation for an API that answers JSON only.

DRF's default parses the Accept header into media types and ranks them on every request; an
upload paid about 4% of its CPU for it. Here a request that accepts anything (no Accept, or
`*/*`) or JSON exactly, and asks for no format in the URL, gets the one renderer at once;
every other request is negotiated as DRF does (406 when JSON is not acceptable).
"""

from collections.abc import Sequence
from typing import Any

from rest_framework.negotiation import DefaultContentNegotiation
from rest_framework.renderers import BaseRenderer
from rest_framework.request import Request

_ACCEPTS_JSON = frozenset({"", "*/*", "application/json"})


class JsonContentNegotiation(DefaultContentNegotiation):
    def select_renderer(
        self, request: Request, renderers: Sequence[BaseRenderer], format_suffix: Any = None
    ) -> tuple[BaseRenderer, str]:
        if (
            len(renderers) == 1
            and renderers[0].media_type == "application/json"
            and format_suffix is None
            and request.META.get("HTTP_ACCEPT", "").strip() in _ACCEPTS_JSON
            and self.settings.URL_FORMAT_OVERRIDE not in request.GET
        ):
            return renderers[0], renderers[0].media_type
        return super().select_renderer(request, renderers, format_suffix)
