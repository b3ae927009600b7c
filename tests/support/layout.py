"""What the browser tests check of a page's layout."""

from playwright.sync_api import Page


def cells_off_screen(page: Page, cells: str) -> int:
    """How many of the elements matching `cells` are not wholly inside the viewport's width
    (or have no width at all): a table that scrolls sideways in its box has some."""
    return page.evaluate(
        """([cells, width]) => [...document.querySelectorAll(cells)]
            .map((cell) => cell.getBoundingClientRect())
            .filter((box) => box.width === 0 || box.left < 0 || box.right > width + 0.5).length""",
        [cells, page.viewport_size["width"]],
    )
