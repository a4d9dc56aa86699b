"""How many intra-op threads torch uses for torchcal's many small solves.

A calibration fit is thousands of small operations (Jacobians of a few thousand rows and ~40
columns, 64-wide MLP layers on batches of 128, 80x80 ridge solves): each is over in well under
a millisecond, and splitting it across threads costs more in synchronization than it gains.
When other processes share the cores it costs far more: a thread of an operation waits for a
core while the others spin at the barrier. On the project's 2-core machine under load, one
thread trained the twin's MLP head fold 14x faster than two and searched the MMA-ELM's hidden
layer 4x faster, with bit-identical weights (MLP) and weights equal to 3e-16 (MMA-ELM); the
k-means of the configuration folds took 0.17 s instead of 0.7-2.4 s, with the same folds
(docs/benchmarks.md, "Where a fit's time goes"). What uses the cores well is independent work
side by side (a study's worker processes), not one small matrix split in two.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from threadpoolctl import threadpool_limits

#: Intra-op threads of a fit (:func:`fit_threads`).
FIT_THREADS = 1


@contextmanager
def fit_threads(threads: int = FIT_THREADS) -> Iterator[None]:
    """Run the body with ``threads`` torch intra-op threads, restoring the previous count after.

    The OpenMP and BLAS pools of numpy, scipy and scikit-learn (the k-means of the folds) get the
    same limit (threadpoolctl). Never raises the count: a process that already runs on fewer
    threads (a study worker) keeps them.
    """
    previous = torch.get_num_threads()
    count = max(1, min(threads, previous))
    torch.set_num_threads(count)
    try:
        with threadpool_limits(limits=count):
            yield
    finally:
        torch.set_num_threads(previous)
