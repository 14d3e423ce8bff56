"""How much of a mapped file is resident in this process (Linux's smaps)."""

from __future__ import annotations

from pathlib import Path


def mapped_kib(path: Path) -> int:
    """Resident KiB of this process's mappings of ``path`` (Linux's smaps; 0 unmapped).

    Found by searching the text for the path's header lines (a process with numba and
    torch loaded has tens of thousands of smaps lines: splitting them all for each of
    hundreds of reads cost most of a test's time); a mapping's ``Rss:`` is the first
    after its header."""
    text = Path("/proc/self/smaps").read_text()
    header_end = f" {path}\n"
    total = 0
    at = text.find(header_end)
    while at != -1:
        rss = text.index("\nRss:", at)
        total += int(text[rss + 5 : text.index("kB", rss)])
        at = text.find(header_end, at + len(header_end))
    return total
