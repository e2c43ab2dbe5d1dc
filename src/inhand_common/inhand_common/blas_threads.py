"""One BLAS thread per process.

numpy's OpenBLAS starts a thread per core for every matrix product above a small size. Our
products are tall and thin (a 640x480 image's points times a 3x3 rotation, a plane's normal
against every point), where splitting the rows saves little, and the graph runs several
processes on few cores: the BLAS threads then wait for cores the other nodes hold. Measured
on a 2-core machine with another job running, ``(307200, 3) @ (3, 3)`` took 76-80 ms with
OpenBLAS's two threads and 6 ms with one. Every node and the offline tools that do what the
nodes do call :func:`single_threaded_blas` at start.
"""

from __future__ import annotations

__all__ = ['single_threaded_blas']


def single_threaded_blas() -> None:
    """Limit the BLAS libraries loaded in this process (numpy's OpenBLAS) to one thread."""
    from threadpoolctl import threadpool_limits  # type: ignore[import-untyped]
    threadpool_limits(limits=1, user_api='blas')
