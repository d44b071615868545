"""Work spread over spawned worker processes: results in order, a worker that dies one clear
error, and a script without the `__main__` guard stopped with one, not workers starting
workers without end."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bid_sim.errors import BidError
from bid_sim.parallel import WorkerDied, map_parallel, require_main_process, run_parallel


def test_map_parallel_keeps_the_order_of_its_items():
    items = list(range(-7, 7))
    assert map_parallel(abs, items, 3) == [abs(i) for i in items]
    assert map_parallel(abs, items[:1], 3) == [7]  # one item: in this process
    assert map_parallel(abs, [], 3) == []
    require_main_process()  # pytest is no worker


def _script(tmp_path: Path, body: str) -> subprocess.CompletedProcess:
    script = tmp_path / "script.py"
    script.write_text(body)
    return subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("guarded", [True, False])
def test_a_script_without_the_guard_gets_one_error(tmp_path, guarded):
    work = "print(map_parallel(abs, [1, -2, 3], 2))"
    body = "from bid_sim.parallel import map_parallel\n" + (
        f'if __name__ == "__main__":\n    {work}\n' if guarded else f"{work}\n")
    done = _script(tmp_path, body)
    if guarded:
        assert (done.returncode, done.stdout) == (0, "[1, 2, 3]\n")
    else:
        assert done.returncode != 0
        assert 'if __name__ == "__main__":' in done.stderr.strip().splitlines()[-1]


def test_caching_frames_from_a_script_without_the_guard_leaves_no_files(recorded, tmp_path):
    """The frame cache is decoded in workers; a worker running the script's top level again
    must refuse before it writes a cache-sized file of its own."""
    folder = tmp_path / "rec"
    shutil.copytree(recorded, folder, ignore=shutil.ignore_patterns(".bid_cache"))
    done = _script(tmp_path, "import os\nos.cpu_count = lambda: 2  # two workers on any machine\n"
                             "from bid_model.recordings import open_every_frame\n"
                             f"open_every_frame({str(folder)!r}, (24, 72))\n")
    assert done.returncode != 0
    assert 'if __name__ == "__main__":' in done.stderr
    assert not list(folder.rglob("*.tmp")) and not list(folder.rglob("*.u8"))


def test_a_worker_refuses_to_start_workers():
    assert map_parallel(_refusal, [0, 1], 2) == ["refused", "refused"]


def _refusal(_item) -> str:
    try:
        require_main_process()
    except BidError as e:
        return "refused" if "__main__" in str(e) else str(e)
    return "started"


def test_a_worker_that_dies_is_one_error_not_one_per_item_left():
    """An episode's error goes to on_error and the others go on; a worker process that dies
    (out of memory, a crash) leaves no pool to run them: one WorkerDied."""
    done, errors = [], []
    run_parallel(_fails_on_two, [1, 2, 3], 2, lambda item, result: done.append(result),
                 on_error=lambda item, e: errors.append((item, str(e))))
    assert (sorted(done), errors) == ([1, 3], [(2, "two")])
    with pytest.raises(WorkerDied, match="worker process died"):
        run_parallel(_dies_on_two, [1, 2, 3, 4, 5, 6], 2, lambda item, result: done.append(result),
                     on_error=lambda item, e: errors.append((item, str(e))))
    assert errors == [(2, "two")]


def _fails_on_two(item: int) -> int:
    if item == 2:
        raise ValueError("two")
    return item


def _dies_on_two(item: int) -> int:
    if item == 2:
        os._exit(3)
    return item
