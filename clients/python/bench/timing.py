"""The benches' one timer: the median of repeated calls, on ``time.perf_counter``."""
import statistics
import time


def median(fn, runs):
    """Median seconds of ``runs`` calls of ``fn``, and its last result."""
    times, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def median_ms(fn, runs):
    """Median milliseconds of ``runs`` calls of ``fn``."""
    return median(fn, runs)[0] * 1e3
