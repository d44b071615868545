"""Running one function over many items in worker processes, results as they complete.

Workers are spawned, not forked: the parent may hold SUMO and torch threads. libsumo allows
one simulation per process, so parallel episodes need processes, not threads.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from functools import partial
from typing import Any

from bid_sim.errors import BidError

# A spawned worker imports the script that started it again, its top level included.
GUARD_HINT = 'a script that calls this needs its work under `if __name__ == "__main__":`'


class WorkerDied(BidError):
    """A worker process died before it finished: the pool cannot run the items left."""


def require_main_process() -> None:
    """BidError in a worker process: there, starting workers means a script without the guard
    was run again in a worker, and would start workers without end."""
    if mp.parent_process() is not None:
        raise BidError(f"worker processes cannot start worker processes; {GUARD_HINT}")


def run_parallel(fn: Callable[[Any], Any], items: Sequence[Any], workers: int,
                 on_result: Callable[[Any, Any], None],
                 on_error: Callable[[Any, Exception], None] | None = None,
                 initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> None:
    """Calls fn(item) for every item on up to `workers` processes (in this process when
    workers <= 1 or there is one item) and reports each as it completes: on_result(item,
    result), or on_error(item, exception) when given (else the exception propagates and the
    items not yet started are cancelled). A worker process that dies (out of memory, a crash,
    or one that ran a script without the `__main__` guard) breaks the pool: that is one
    WorkerDied, not on_error for every item left. fn, items and initargs must pickle. A worker
    process refuses to start workers of its own (GUARD_HINT)."""
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
    require_main_process()
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
                    except BrokenProcessPool as e:
                        raise WorkerDied("a worker process died before it finished "
                                         f"(out of memory, or {GUARD_HINT})") from e
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


def _numbered(fn: Callable[[Any], Any], numbered: tuple[int, Any]) -> tuple[int, Any]:
    return numbered[0], fn(numbered[1])


def map_parallel(fn: Callable[[Any], Any], items: Sequence[Any], workers: int) -> list[Any]:
    """[fn(item) for item in items], on up to `workers` processes as run_parallel runs them; a
    worker process that dies (out of memory, a crash, or one that ran a script without the
    `__main__` guard) is one WorkerDied (run_parallel), not a traceback from the process pool."""
    results: dict[int, Any] = {}
    run_parallel(partial(_numbered, fn), list(enumerate(items)), workers,
                 lambda _item, done: results.__setitem__(*done))
    return [results[i] for i in range(len(items))]
