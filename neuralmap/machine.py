"""The machine a run measured on: CPU model, cores, torch threads, load.

Benchmarks, training runs and studies record it beside their numbers (in the provenance
of their ``summary.md``), so a stamped page says what the figures were measured on — on a
shared machine the load matters as much as the CPU.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

__all__ = ["cpu_model", "machine"]


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; the platform's processor elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """The machine a run measured on: CPU model, logical cores, torch threads, the
    ``OMP_NUM_THREADS`` setting and the 1-minute load average when asked."""
    try:
        import torch

        threads: int | None = torch.get_num_threads()
    except ImportError:  # pragma: no cover - torch is a dependency
        threads = None
    try:
        load: float | None = round(os.getloadavg()[0], 2)
    except OSError:  # pragma: no cover - not on every platform
        load = None
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "torch_threads": threads,
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "load_1min": load,
            "python": platform.python_version()}
