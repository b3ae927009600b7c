"""The benchmarks' figures: matplotlib without a display, set up once, and one way to save."""

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only: no display, whatever the environment says
import matplotlib.pyplot as plt
from matplotlib.figure import Figure

__all__ = ["ENGINE_STYLES", "engine_label", "machine_line", "plt", "save_figure"]

# How a line shows its engines (bench.stack.ENGINES): SQLite + disk thin with round markers,
# PostgreSQL + S3 thick with hollow ones.
ENGINE_STYLES: dict[str, dict[str, Any]] = {
    "sqlite-disk": {"linewidth": 1.2},
    "postgres-s3": {"linewidth": 2.4, "markerfacecolor": "none"},
}
_ENGINE_SHORT = {"sqlite-disk": "SQLite+disk", "postgres-s3": "PG+S3"}


def engine_label(engines: str, present: list[str]) -> str:
    """A legend's prefix naming a line's engines, when the figure shows more than one."""
    return f"{_ENGINE_SHORT.get(engines, engines)}, " if len(present) > 1 else ""


def machine_line(report: dict[str, Any]) -> str:
    """The CPU, cores and date of a run, for a figure's title."""
    machine = report["machine"]
    return f"{machine['cpu_model']}, {machine['logical_cores']} cores, {report['date']}"


def save_figure(figure: Figure, path: Path, title: str, *, fontsize: float = 9) -> None:
    """Title the figure, lay it out, write it as a PNG and free it."""
    figure.suptitle(title, fontsize=fontsize)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)
