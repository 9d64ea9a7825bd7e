"""One BLAS thread for a selfcal process: its linear algebra is on small matrices.

selfcal's fits and checks multiply, factor and decompose matrices of a few thousand rows
by ~12 columns. OpenBLAS's default of a thread per core brings nothing there: its extra
threads busy-wait between calls. Alone on the machine they burn a second core for the
same wall time. Beside other work, they slow the refits down: a server's request threads,
other refit workers, or another replay.

Measured on this repository's 2-core machine (a 120-day replay, 2026-12-02):
* alone, it took 3.8-4.0 s wall and 3.9-4.1 s CPU with one thread, against 4.1-4.6 s
  wall and 6.5-7.0 s CPU with the default;
* with the other core busy, its refits took 2.5 s with one thread against 4.6-4.7 s.

The results are the same bit for bit. Six replays were hashed both ways: poses and samples
level, a bias step, the calibrator's own scheduler and 120 days of a temperature effect.

:func:`one_blas_thread` is called by the ``selfcal`` command line at its start, so it
covers ``serve``, ``worker``, ``calibrate``, ``replay`` and the processes they start.
A thread count the user set in the environment is kept. The fleet replay's engines set
it per device (:func:`selfcal.replay._replay_one`). A program that uses the Python API
in its own process can call this function itself, or use ``threadpoolctl``.
"""

from __future__ import annotations

import os

from threadpoolctl import threadpool_limits

#: The variables through which a user chooses a BLAS thread count. If one of them is set,
#: it is kept.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS", "OMP_NUM_THREADS")
#: The variables this module sets, for the BLAS libraries loaded later and for child processes.
#: ``OMP_NUM_THREADS`` is left alone: it also sizes other libraries' thread pools.
SET_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def user_thread_count() -> str | None:
    """The first of :data:`THREAD_VARIABLES` set in the environment, as ``NAME=value``; None if none is."""
    for name in THREAD_VARIABLES:
        if os.environ.get(name):
            return f"{name}={os.environ[name]}"
    return None


def one_blas_thread() -> bool:
    """Run this process's BLAS with one thread, unless the user chose a count in the environment.

    Two steps:
    * the libraries already loaded (numpy's OpenBLAS) are set through ``threadpoolctl``;
    * the variables of :data:`SET_VARIABLES` are set, so that a library loaded later reads
      them at its start, and so that a child process inherits them.

    Returns True if it set one thread, and False if it kept the user's choice.
    """
    if user_thread_count() is not None:
        return False
    for name in SET_VARIABLES:
        os.environ[name] = "1"
    threadpool_limits(limits=1, user_api="blas")  # process-wide, until the process ends
    return True
