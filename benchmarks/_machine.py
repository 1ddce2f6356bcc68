"""The machine a benchmark ran on, for its header (shared by the benchmark scripts)."""

from __future__ import annotations

import pathlib
import platform


def cpu_model() -> str:
    """The processor's name (Linux: /proc/cpuinfo), for comparing runs across sittings:
    the same tests have run 1.8 times faster on one sitting's machine than on another's.
    Elsewhere ``platform.processor()``, else the architecture."""
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
