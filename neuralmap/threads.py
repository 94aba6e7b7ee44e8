"""Torch CPU threads: one thread for small factorisations, and the thread count of a run.

Two torch threads on a 2-core machine that is also running something else make small
batched operations collapse: every parallel region waits for a core the other job holds.
Measured on the shared 2-core machine: one ``cholesky_ex`` of a 15×15 matrix takes 3 µs on
one thread and up to 8 ms on two; ``neuralmap-gins`` on a 30 k-record log took 20 s with two
threads against 10 s with one. A factorisation of small matrices gains nothing from a
second thread (torch loops over the batch serially and LAPACK does not split a 15×15
factorisation), so `one_thread` runs such calls on one thread whatever the process
setting; the stages' defaults (``threads: 1`` in the study configs, ``--threads 1`` of the
command-line tools) come from the measurements in the README.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["SMALL_MATRIX_MAX", "one_thread", "set_threads"]

#: Matrices up to this size are factorised on one thread (`one_thread`).
SMALL_MATRIX_MAX = 64


@contextmanager
def one_thread(n: int = 0) -> Iterator[None]:
    """Runs the block on one torch thread when ``n <= SMALL_MATRIX_MAX`` (restored after).

    The numbers are the same as on more threads (the work inside is serial anyway); only
    the waits of a parallel region on a busy machine go. Not meant for blocks that other
    Python threads run concurrently (the thread count is process-wide).

    Args:
        n: Size of the matrices factorised inside (0 = small).
    """
    before = torch.get_num_threads()
    if before == 1 or n > SMALL_MATRIX_MAX:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def set_threads(threads: int | None, *, option: str = "--threads") -> None:
    """``torch.set_num_threads(threads)`` after a check; None keeps torch's setting.

    Raises:
        NeuralMapError: ``threads`` is not an integer >= 1, naming ``option``.
    """
    if threads is None:
        return
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        from neuralmap.exceptions import NeuralMapError

        raise NeuralMapError(f"{option} must be an integer >= 1 (torch CPU threads), got "
                             f"{threads!r}; 1 is the measured default on a shared machine.")
    torch.set_num_threads(threads)
