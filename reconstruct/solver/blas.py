"""The solve's BLAS threads: one, except for the Anderson mix.

The solver's BLAS products are small or already split over the solver's own `workers` threads (X-step points,
W-step components and Gram batches, chunked products). A second OpenBLAS thread per product then gains nothing
and its idle spinning takes the core that those threads or the next step need, several times the CPU time of the
products themselves on a busy machine. The products give the same values to the bit with one thread, except the
Anderson mix's: with a one-iterate history its products are BLAS dot products, whose sums OpenBLAS splits over its
threads. The mix keeps the caller's threads (`outer_blas_threads`), so that a solve gives the same result as it did
without the limit.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from contextvars import ContextVar
from typing import Any

from threadpoolctl import ThreadpoolController

# The libraries found by `one_blas_thread` and their callers' thread counts (threadpoolctl's info()); None outside it.
_OUTER: ContextVar[tuple[ThreadpoolController, list[dict[str, Any]]] | None] = ContextVar(
    "outer_blas_threads", default=None
)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """The block runs with one BLAS thread (process-wide, as BLAS libraries count threads); `outer_blas_threads`
    inside it gives the caller's counts back."""
    # Looked up per call, not cached: a library loaded after a cached lookup (scipy's own OpenBLAS) would be missed.
    controller = ThreadpoolController()
    token = _OUTER.set((controller, controller.info()))
    try:
        with controller.limit(limits=1, user_api="blas"):
            yield
    finally:
        _OUTER.reset(token)


def outer_blas_threads() -> AbstractContextManager[Any]:
    """Inside `one_blas_thread`: the caller's BLAS thread counts for the block; elsewhere nothing changes."""
    outer = _OUTER.get()
    return nullcontext() if outer is None else outer[0].limit(limits=outer[1])
