"""Template filters of the paginated pages."""

from collections.abc import Iterator

from django import template
from django.core.paginator import Page

register = template.Library()


@register.filter
def elided_pages(page: Page) -> Iterator[int | str]:
    """The page numbers to link: the first and last, and two either side of the current one
    (Paginator.ELLIPSIS where some are left out)."""
    return page.paginator.get_elided_page_range(page.number, on_each_side=2, on_ends=1)
