"""The benchmarks' figures: matplotlib without a display, set up once, and one way to save."""

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only: no display, whatever the environment says
import matplotlib.pyplot as plt
from matplotlib.figure import Figure

__all__ = ["machine_line", "plt", "save_figure"]


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
