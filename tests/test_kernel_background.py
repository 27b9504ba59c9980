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
