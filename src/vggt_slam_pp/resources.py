"""Process memory figures for reports and benchmarks (Linux ``/proc`` where available)."""

from __future__ import annotations

import resource


def _status_mb(field: str) -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB since it started or since :func:`reset_peak_rss`
    (``VmHWM``; ``getrusage`` elsewhere, which Linux carries across ``exec``: a spawned child would
    report its parent's peak)."""
    hwm = _status_mb("VmHWM")
    return hwm if hwm is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb() -> float:
    """Current resident memory of this process in MiB (the peak where ``/proc`` is missing)."""
    rss = _status_mb("VmRSS")
    return rss if rss is not None else peak_rss_mb()


def reset_peak_rss() -> None:
    """Start a new peak-RSS measurement (Linux: ``/proc/self/clear_refs``); a no-op elsewhere."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def release_free_memory() -> None:
    """Hand freed heap pages back to the OS (glibc ``malloc_trim``; a no-op elsewhere). Bursts of
    temporary arrays (re-rasterising many layers after a global optimisation) otherwise leave the
    process's RSS at its high-water mark."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        if libc is not None and hasattr(libc, "malloc_trim"):
            libc.malloc_trim(0)
    except OSError:
        pass
