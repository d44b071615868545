"""Running episodes as Ray tasks on a cluster: `bid record --ray` and `bid evaluate --ray`.

The same contract as bid_sim.parallel.run_parallel, with a Ray cluster instead of a local
process pool. Each task asks for one CPU, so a Ray worker process runs one task at a time:
libsumo's one simulation per process holds, and run_episode closes the simulation in
`finally`, so a reused worker starts the next episode clean. The pool's initializer runs
once per worker process and run (not once per task), so an agent is loaded once per worker.

Tasks write their files (recordings, videos) under the --out folder themselves, so every
node must see that folder at the same path (a shared filesystem); a task on a node that
does not fails with a BidError saying so. Ray is imported only here, and only when asked for.
"""

from __future__ import annotations

import logging
import socket
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from bid_sim.errors import BidError

log = logging.getLogger(__name__)

INSTALL_HINT = "--ray needs Ray: pip install 'bid-sim[cluster]'"

# The run whose initializer this worker process has run (a worker serves many tasks and runs).
_initialised_for: str | None = None


def require_ray():
    """The ray module, or a BidError naming the install command."""
    try:
        import ray
    except ImportError as e:
        raise BidError(INSTALL_HINT) from e
    return ray


def _task(job: tuple, item: Any) -> Any:
    """One item in a Ray worker: the run's initializer first if this worker has not run it."""
    global _initialised_for
    fn, initializer, initargs, run_id, marker = job
    if marker is not None and not Path(marker).exists():
        raise BidError(f"{Path(marker).parent} is not visible on node {socket.gethostname()}; "
                       "put --out on a filesystem every Ray node mounts at the same path")
    if initializer is not None and _initialised_for != run_id:
        initializer(*initargs)
        _initialised_for = run_id
    return fn(item)


def run_ray(fn: Callable[[Any], Any], items: Sequence[Any], address: str | None,
            on_result: Callable[[Any, Any], None],
            on_error: Callable[[Any, Exception], None] | None = None,
            initializer: Callable[..., None] | None = None, initargs: tuple = (),
            shared: Path | None = None) -> None:
    """Calls fn(item) for every item as a Ray task and reports each as it completes, like
    run_parallel: on_result(item, result), or on_error(item, exception) when given (else the
    exception propagates and the tasks not yet finished are cancelled).

    address: a cluster's address (HOST:6379, auto, ray://HOST:10001), or None or "" for
    $RAY_ADDRESS, else the cluster last started on this machine, else a new local instance.
    A process already connected to Ray (ray.init) keeps its connection. shared: a folder the
    tasks write into, which every node must see (checked by each task).
    """
    ray = require_ray()
    if not items:
        return
    started = not ray.is_initialized()
    if started:
        if address:
            _check_reachable(address)
        try:
            ray.init(address=address or None)
        except ConnectionError as e:
            raise BidError(f"no Ray cluster at {address or '$RAY_ADDRESS'} ({e}); start one with "
                           "`ray start --head` or give its address") from e
    run_id = uuid.uuid4().hex
    marker = None if shared is None else Path(shared).resolve() / f".ray-run-{run_id}"
    try:
        if marker is not None:
            marker.write_bytes(b"")
        # One CPU each: a worker process holds one simulation at a time.
        remote = ray.remote(num_cpus=1)(_task)
        job = ray.put((fn, initializer, initargs, run_id, None if marker is None else str(marker)))
        refs = {remote.remote(job, item): item for item in items}
        log.info("%d tasks on Ray (%s CPUs)", len(refs), ray.cluster_resources().get("CPU"))
        _collect(ray, refs, on_result, on_error)
    finally:
        if marker is not None:
            marker.unlink(missing_ok=True)
        if started:
            ray.shutdown()


def _collect(ray, refs: dict, on_result: Callable[[Any, Any], None],
             on_error: Callable[[Any, Exception], None] | None) -> None:
    """Reports each task as it completes; cancels the rest if one raises."""
    pending = list(refs)
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                try:
                    result = ray.get(ref)
                except Exception as e:
                    if on_error is None:
                        if isinstance(_cause(e), BidError):
                            raise _cause(e) from None
                        raise  # Ray's error: its message holds the remote traceback
                    on_error(refs[ref], _cause(e))
                    continue
                on_result(refs[ref], result)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise


def _check_reachable(address: str) -> None:
    """A BidError at once if nothing listens at HOST:PORT (Ray itself retries for minutes)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return  # "auto", "local": Ray resolves those
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except OSError as e:
        raise BidError(f"no Ray cluster answers at {address} ({e.strerror or e}); start one with "
                       "`ray start --head` there, or check the address") from e


def _cause(e: Exception) -> Exception:
    """The task's own exception rather than Ray's wrapper, whose message carries the remote
    traceback; Ray's own errors (a worker died) as they are."""
    cause = getattr(e, "cause", None)
    return cause if isinstance(cause, Exception) else e
