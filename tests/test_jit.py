"""The threads of a kernel call (cutfem.jit): serial below a size, never above the free cores,
numba's thread count put back after every call.  Timings live in studies/contention.py."""

import numba
import numpy as np
import pytest

from cutfem import jit
from cutfem.fem import element_kernels
from cutfem.solvers import sparse_kernels


@pytest.fixture
def load(monkeypatch):
    """Set the other processes' load (cores) that the policy sees."""
    value = {"others": 0.0}
    monkeypatch.setattr(jit, "others_load", lambda: value["others"])
    monkeypatch.setattr(jit, "_usable_cpus", lambda: frozenset({0, 1}))
    return value


def test_small_calls_run_on_the_calling_thread(load):
    assert jit.team(jit.PARALLEL_MIN_BYTES - 1, 2) == 1
    assert jit.team(jit.PARALLEL_MIN_BYTES, 2) == 2


def test_never_more_threads_than_numba_allows_or_the_cores(load, monkeypatch):
    assert jit.team(10**9, 1) == 1  # NUMBA_NUM_THREADS=1 or numba.set_num_threads(1)
    monkeypatch.setattr(jit, "_usable_cpus", lambda: frozenset({3}))  # taskset -c 3
    assert jit.team(10**9, 2) == 1
    monkeypatch.setattr(jit, "_usable_cpus", lambda: frozenset(range(8)))
    assert jit.team(10**9, 4) == 4


@pytest.mark.parametrize("others, expected", [(0.0, 2), (0.29, 2), (0.31, 1), (1.0, 1), (5.0, 1)])
def test_busy_cores_are_not_counted(load, others, expected):
    load["others"] = others
    assert jit.team(10**9, 2) == expected


def test_the_load_of_the_others_is_the_busy_time_less_our_own(monkeypatch):
    """Over a window of 0.5 s the usable cores were busy 0.9 s and this process used 0.4 s of CPU:
    the others used one core's worth."""
    clock = iter([100.0, 100.5, 100.55])
    busy = iter([50.0, 50.9, 51.0])
    own = iter([2.0, 2.4, 2.45])
    monkeypatch.setattr(jit.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(jit.time, "process_time", lambda: next(own))
    monkeypatch.setattr(jit, "_busy_seconds", lambda cpus: next(busy))
    monkeypatch.setattr(jit, "_runnable_others", lambda: 0.0)
    monkeypatch.setattr(jit, "_usable_cpus", lambda: frozenset({0, 1}))
    monkeypatch.setattr(jit, "_state", {"time": None, "busy": None, "own": None, "others": 0.0, "cpus": None})
    assert jit.others_load() == 0.0  # the first sample: the runnable tasks of /proc/loadavg
    assert jit.others_load() == pytest.approx(1.0)
    assert jit.others_load() == pytest.approx(1.0)  # 0.05 s later: no new sample, the same estimate
    assert jit._state["busy"] == 50.9


def test_first_sample_counts_the_runnable_tasks_but_ourselves(monkeypatch, tmp_path):
    monkeypatch.setattr(jit, "_state", {"time": None, "busy": None, "own": None, "others": 0.0, "cpus": None})
    monkeypatch.setattr(jit, "_busy_seconds", lambda cpus: 10.0)
    original = open

    def fake_open(path, *args, **kwargs):
        if path == "/proc/loadavg":
            p = tmp_path / "loadavg"
            p.write_text("1.02 0.80 0.50 3/140 12345\n")
            return original(p, *args, **kwargs)
        return original(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", fake_open)
    assert jit.others_load() == 2.0


def test_without_proc_only_the_size_decides(monkeypatch):
    monkeypatch.setattr(jit, "_state", {"time": None, "busy": None, "own": None, "others": 0.0, "cpus": None})
    monkeypatch.setattr(jit, "_busy_seconds", lambda cpus: None)
    monkeypatch.setattr(jit, "_usable_cpus", lambda: frozenset({0, 1}))
    assert jit.team(10**9, 2) == 2


def test_a_kernel_call_puts_numbas_thread_count_back(load):
    """Small, large and failing calls all leave the calling thread's count as it was, and the
    results are the same bits on one thread and on two."""
    x = np.random.default_rng(0).standard_normal((jit.PARALLEL_MIN_BYTES // 8 + 10, 3))
    before = numba.get_num_threads()
    big_two = sparse_kernels.column_dots(x, x)
    assert numba.get_num_threads() == before
    load["others"] = 1.0
    big_one = sparse_kernels.column_dots(x, x)
    assert numba.get_num_threads() == before
    assert np.array_equal(big_one, big_two)
    small = sparse_kernels.column_dots(x[:10], x[:10])
    assert numba.get_num_threads() == before
    assert np.allclose(small, (x[:10] * x[:10]).sum(axis=0))
    with pytest.raises(numba.core.errors.TypingError):  # a small call that fails: no version for these types
        sparse_kernels._column_dots(x[:10], x[:10], "not an array", np.zeros(3), np.zeros(3))
    assert numba.get_num_threads() == before


def test_the_error_sums_are_the_same_bits_on_one_thread_and_on_two(load):
    """The error norms' block sums end in a sum over the quadrature points: an array reduction
    (``total.sum()``) there was split between the threads by numba, and the H1 error of poisson-cut
    changed in its last digit with the thread count."""
    rng = np.random.default_rng(0)
    b, nq = 20000, 11
    table, types = rng.random((6, 4, 3)), rng.integers(0, 6, b)
    local, exact, w = rng.random((b, 4)), rng.random((b, nq, 3)), rng.random((b, nq))
    phi = rng.random((b, nq, 4))
    results = []
    for others in (0.0, 1.0):  # two threads, then the calling thread alone
        load["others"] = others
        results.append((element_kernels.cell_gradient_error(table, types, local, exact, w, np.zeros((0, 3))),
                        element_kernels.cell_value_error(phi, local[:, :, None], exact[:, :, :1], w)))
    assert results[0] == results[1]


def test_the_policy_is_used_by_every_kernel_call(load, monkeypatch):
    """_Kernel asks jit.team with the bytes of its array arguments."""
    seen = []
    monkeypatch.setattr(jit, "team", lambda nbytes, limit: seen.append((nbytes, limit)) or 1)
    x = np.ones((1000, 3))
    sparse_kernels.column_dots(x, x)
    (nbytes, limit), = seen
    assert 2 * x.nbytes <= nbytes <= 2 * x.nbytes + 256 and limit == numba.get_num_threads()
