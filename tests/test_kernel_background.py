"""The fused UKF kernel compiled in a child process while a command sets up
(bondgraph.inference.ukf_numba.compile_in_background): started only when
numba's cache does not hold the kernel yet (the marker file), the cache
folder can be made and background compiles are on; kernel() waits for the child, then loads the kernel and
marks it cached."""

import sys

import pytest

pytest.importorskip("numba")

from bondgraph.inference import ukf_numba  # noqa: E402


class FakeChild:
    def __init__(self, argv, **kw):
        self.argv, self.waited, self.running = argv, False, True
        FakeChild.made.append(self)

    def poll(self):
        return None if self.running else 0

    def wait(self):
        self.waited, self.running = True, False
        return 0

    def terminate(self):
        self.running = False


@pytest.fixture
def fresh(tmp_path, monkeypatch):
    """No kernel loaded in this process, an empty kernel cache folder, Popen faked."""
    kern, _ = ukf_numba.kernel()            # compiled or loaded once: numba's cache holds it
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("BONDGRAPH_COMPILE_AHEAD", raising=False)
    monkeypatch.setattr(ukf_numba, "ahead_workers", lambda: 1)
    monkeypatch.setattr(ukf_numba, "_KERNEL", [])
    monkeypatch.setattr(ukf_numba, "_BACKGROUND", [])
    monkeypatch.setattr(ukf_numba.subprocess, "Popen", FakeChild)
    FakeChild.made = []
    return tmp_path


def test_a_child_compiles_when_the_cache_lacks_the_kernel_and_kernel_waits_for_it(fresh):
    assert not ukf_numba._cached_marker().exists()
    assert ukf_numba.compile_in_background()
    (child,) = FakeChild.made
    assert child.argv[0] == sys.executable and "kernel()" in child.argv[-1]
    assert not ukf_numba.compile_in_background()        # one child at a time
    k, _ = ukf_numba.kernel()
    assert child.waited and k is ukf_numba._KERNEL[0]
    assert ukf_numba._cached_marker().exists()
    ukf_numba._KERNEL.clear()
    assert not ukf_numba.compile_in_background()        # marked: no second child
    assert len(FakeChild.made) == 1


def test_no_child_when_background_compiles_are_off(fresh, monkeypatch):
    monkeypatch.setattr(ukf_numba, "ahead_workers", lambda: 0)
    assert not ukf_numba.compile_in_background()
    assert FakeChild.made == []


def test_the_marker_names_this_module_and_numbas_cache(fresh, monkeypatch):
    a = ukf_numba._cached_marker()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(fresh / "elsewhere"))
    assert ukf_numba._cached_marker() != a and a.parent == fresh


def test_no_child_when_the_cache_folder_cannot_be_made(fresh, monkeypatch):
    blocker = fresh / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("BONDGRAPH_CACHE_DIR", str(blocker / "cache"))
    assert not ukf_numba.compile_in_background()
    assert FakeChild.made == []


def test_work_queued_while_compiling_runs_during_the_wait_at_low_priority(fresh, monkeypatch):
    """ukf_numba.while_compiling: the task starts when kernel() begins to
    wait for the child (not before), runs while it waits (the fake child's
    wait returns only after the task has started), sees its event set when
    the wait ends, and runs at nice 19 on Linux."""
    import os
    import threading
    started, seen = threading.Event(), {}

    def wait_for_task(self):
        assert started.wait(10), "the task did not start while kernel() waited"
        self.waited, self.running = True, False
        return 0

    monkeypatch.setattr(FakeChild, "wait", wait_for_task)

    def task(done):
        seen["done_at_start"] = done.is_set()
        if sys.platform.startswith("linux"):
            seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        started.set()
        seen["done_after"] = done.wait(10)

    assert not ukf_numba.while_compiling(task)          # no child: no wait to fill
    assert ukf_numba.compile_in_background()
    assert ukf_numba.while_compiling(task)
    assert not started.is_set()                         # queued, not started
    ukf_numba.kernel()
    for _ in range(100):
        if "done_after" in seen:
            break
        threading.Event().wait(0.05)
    assert seen["done_at_start"] is False and seen["done_after"] is True
    if sys.platform.startswith("linux"):
        assert seen["nice"] == 19
    assert ukf_numba._WAITERS == []
    assert not ukf_numba.while_compiling(task)          # the kernel is loaded now


def test_a_task_is_dropped_when_the_child_finished_before_the_wait(fresh):
    ran = []
    assert ukf_numba.compile_in_background()
    assert ukf_numba.while_compiling(lambda done: ran.append(1))
    FakeChild.made[0].running = False                   # done before anyone waited
    ukf_numba.kernel()
    assert ran == [] and ukf_numba._WAITERS == []
