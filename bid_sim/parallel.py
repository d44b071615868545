"""Running one function over many items in worker processes, results as they complete.

Workers are spawned, not forked: the parent may hold SUMO and torch threads. libsumo allows
one simulation per process, so parallel episodes need processes, not threads.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any


def run_parallel(fn: Callable[[Any], Any], items: Sequence[Any], workers: int,
                 on_result: Callable[[Any, Any], None],
                 on_error: Callable[[Any, Exception], None] | None = None,
                 initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> None:
    """Calls fn(item) for every item on up to `workers` processes (in this process when
    workers <= 1 or there is one item) and reports each as it completes: on_result(item,
    result), or on_error(item, exception) when given (else the exception propagates and the
    items not yet started are cancelled). fn, items and initargs must pickle."""
    if workers <= 1 or len(items) <= 1:
        if initializer is not None:
            initializer(*initargs)
        for item in items:
            try:
                result = fn(item)
            except Exception as e:
                if on_error is None:
                    raise
                on_error(item, e)
                continue
            on_result(item, result)
        return
    with ProcessPoolExecutor(min(workers, len(items)), mp_context=mp.get_context("spawn"),
                             initializer=initializer, initargs=initargs) as pool:
        futures: dict[Future, Any] = {pool.submit(fn, item): item for item in items}
        pending = set(futures)
        try:
            while pending:
                ready, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in ready:
                    try:
                        result = fut.result()
                    except Exception as e:
                        if on_error is None:
                            raise
                        on_error(futures[fut], e)
                        continue
                    on_result(futures[fut], result)
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise
