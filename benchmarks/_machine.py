"""The host a benchmark ran on, for its header: the 2-core machine is not
always the same CPU (an AMD EPYC and an Intel Xeon so far, ~35-40 % apart in
the compiled fits), so figures from different runs compare only with it."""

from __future__ import annotations

import os
import platform


def cpu() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else ``platform.processor()``."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def host() -> str:
    """``cpu()``, the CPU count and the load average (1 / 5 min) now."""
    load = os.getloadavg()
    return f"{cpu()}, {os.cpu_count()} CPUs, load average {load[0]:.1f} / {load[1]:.1f}"
