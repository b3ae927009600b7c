"""How far a long check has gone, shown on a terminal: one bar on stderr, drawn again in place
as the check moves, and nothing at all when stderr is not a terminal (piped into a file or a
script), so that a log holds only the report and its verdict.

An export's check reads its MCAP file twice (its SM3, then its messages), then checks the
bundle's records: the bar follows the bytes read (`ReadCounted` around the file) and then the
records checked (`verify`'s `progress`).
"""

from pathlib import Path
from typing import IO, Any, TextIO

BAR_WIDTH = 30
_MIB = 1024 * 1024


class ProgressBar:
    """One line on `stream`, drawn only if it is a terminal; each stage's label, a bar, the
    percentage and how much of how much (bytes in MiB)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.shown = stream.isatty()
        self._line = ""

    def show(self, stage: str, done: int, total: int, *, in_bytes: bool = False) -> None:
        if not self.shown:
            return
        fraction = min(done / total, 1.0) if total > 0 else 0.0
        filled = round(fraction * BAR_WIDTH)
        bar = "#" * filled + "." * (BAR_WIDTH - filled)
        if in_bytes:
            amount = f"{min(done, total) / _MIB:,.1f} of {total / _MIB:,.1f} MiB"
        else:
            amount = f"{min(done, total):,} of {total:,}"
        line = f"{stage} [{bar}] {fraction:4.0%}  {amount}"
        if line != self._line:  # drawn again only when what it says changes
            self.stream.write("\r" + line.ljust(len(self._line)))
            self.stream.flush()
            self._line = line

    def close(self) -> None:
        """The bar's line wiped, so that what follows starts on a clean line."""
        if self.shown and self._line:
            self.stream.write("\r" + " " * len(self._line) + "\r")
            self.stream.flush()
            self._line = ""


class ReadCounted:
    """A binary file whose reads move the bar: `passes` reads of it from its start are the
    whole stage (the MCAP file is read twice). Anything else is the file's own."""

    def __init__(self, source: IO[bytes], bar: ProgressBar, *, stage: str, passes: int) -> None:
        self._source = source
        self._bar = bar
        self._stage = stage
        self._total = Path(source.name).stat().st_size * passes
        self._read = 0
        self._next = 0  # drawn again once this many bytes are read (every MiB at most)

    def read(self, size: int = -1) -> bytes:
        data = self._source.read(size)
        self._read += len(data)
        if self._read >= self._next:
            self._bar.show(self._stage, self._read, self._total, in_bytes=True)
            self._next = self._read + _MIB
        return data

    def __getattr__(self, name: str) -> Any:
        return getattr(self._source, name)


def bundle_records_stated(bundle: Path) -> int:
    """How many records a bundle in its canonical form holds, by its lines (a head line,
    `"records":[`, a line a record, `]}`): the bar's whole, never a check."""
    with bundle.open("rb") as source:
        return max(sum(1 for _ in source) - 3, 0)
