"""The run over levels (cutfem.run): garbage collection between levels, fields, the progress
line, failures, the records and their rates, the table and the JSON."""

import json
import re
import subprocess

import numpy as np
import pytest

import cutfem
from cutfem.runs.registry import register


def test_a_level_after_a_long_one_starts_by_collecting_the_garbage(monkeypatch):
    """run() collects the process's garbage before a level when the level before it (in this
    process) ran COLLECT_AFTER seconds or more: the objects of a dropped result that refer to each
    other (as a cut and its element sets do) are freed before the new level allocates; after a
    short level, or with the collector turned off, nothing is collected."""
    import gc
    import weakref

    from cutfem.runs import runner

    @register("test-garbage", levels=[0.5], level_name="step")
    def level(step):
        return {"h": step, "dofs": 1}

    class Cycle:
        def __init__(self):
            self.me = self

    was_enabled, thresholds = gc.isenabled(), gc.get_threshold()
    gc.set_threshold(10**9)  # no automatic collection: only run() may collect
    try:
        for threshold, enabled, freed in ((float("inf"), True, False), (0.0, False, False), (0.0, True, True)):
            monkeypatch.setattr(runner, "COLLECT_AFTER", threshold)
            (gc.enable if enabled else gc.disable)()
            cutfem.run("test-garbage")  # sets the last level's time
            c = Cycle()
            ref = weakref.ref(c)
            del c
            cutfem.run("test-garbage")
            assert (ref() is None) == freed, (threshold, enabled)
    finally:
        gc.set_threshold(*thresholds)
        (gc.enable if was_enabled else gc.disable)()


def test_keep_fields_false_frees_what_the_fields_are_built_from():
    """run(keep_fields=False) drops each record's fields as its level finishes, so the objects they
    would be built from are freed before the next level; by default the records keep them."""
    import weakref

    from cutfem.runs.registry import LazyFields

    class Heavy:
        pass

    refs = []

    @register("test-fields", levels=[0.5, 0.25], level_name="step")
    def level(step):
        heavy = Heavy()
        refs.append(weakref.ref(heavy))
        return {"h": step, "dofs": 1, "fields": LazyFields(lambda: {"heavy": heavy})}

    kept = cutfem.run("test-fields")
    assert [r["fields"]["heavy"] for r in kept.records] == [ref() for ref in refs] and all(ref() is not None for ref in refs)
    refs.clear()
    dropped = cutfem.run("test-fields", keep_fields=False)
    assert all("fields" not in r for r in dropped.records)
    assert [ref() for ref in refs] == [None, None]


def test_progress_line_shows_the_stages_of_long_levels(monkeypatch, capsys):
    """A level past STAGES_AFTER seconds lists its stages on its progress line, in order, with
    their times; a shorter one keeps its short line; nothing is reported outside run()."""
    import time

    from cutfem.runs import runner

    @register("test-stages", levels=[1.0, 2.0], level_name="n")
    def staged(n):
        t = runner.Timer()
        with t("geometry"):
            pass
        with t("solve"):
            time.sleep(0.25 * (n - 1))
        return {"h": 1.0 / n, "dofs": 1, "time": dict(t)}

    monkeypatch.setattr(runner, "STAGES_AFTER", 0.1)
    cutfem.run("test-stages", progress=True)
    lines = capsys.readouterr().err.splitlines()
    assert re.fullmatch(r"\[1/2\] test-stages n=1\.0 \.\.\. done in \d+\.\d\d s", lines[0])  # at once: no stages
    m = re.fullmatch(r"\[2/2\] test-stages n=2\.0 \.\.\. geometry \d+\.\d\d s, solve (\d+\.\d\d) s, done in \d+\.\d\d s", lines[1])
    assert m and float(m.group(1)) >= 0.25
    assert runner._STAGE_LISTENER.get() is None  # reset after the run

    def line_of(name, stages):
        """The progress line of a one-level problem that runs ``stages`` ((stage, seconds) in order)."""

        @register(name, levels=[1.0], level_name="n")
        def staged_again(n):
            t = runner.Timer()
            for stage, seconds in stages:
                with t(stage):
                    time.sleep(seconds)
            return {"h": 1.0 / n, "dofs": 1, "time": dict(t)}

        cutfem.run(name, progress=True)
        return capsys.readouterr().err.strip()

    # a stage entered again right after itself (the matrix, then the load) is one entry
    line = line_of("test-stages-again", [("assembly", 0), ("assembly", 0.15), ("solve", 0), ("assembly", 0)])
    assert re.fullmatch(r"\[1/1\] test-stages-again n=1\.0 \.\.\. assembly \d+\.\d\d s, solve \d+\.\d\d s, "
                        r"assembly \d+\.\d\d s, done in \d+\.\d\d s", line), line
    monkeypatch.setattr(runner, "STAGES_AFTER", 0.0)  # each stage printed as it ends: the second as "+ s"
    line = line_of("test-stages-shown", [("assembly", 0), ("assembly", 0), ("solve", 0)])
    assert re.fullmatch(r"\[1/1\] test-stages-shown n=1\.0 \.\.\. assembly \d+\.\d\d s, \+\d+\.\d\d s, solve \d+\.\d\d s, "
                        r"done in \d+\.\d\d s", line), line
    with runner.Timer()("outside"):
        pass
    assert capsys.readouterr().err == ""


def test_the_progress_line_says_when_cutfem_compiles_its_kernels(monkeypatch, capsys):
    """The first compilation of a function of the cutfem package (numba's cache is empty after an
    install) is announced on the progress line, once a process; a user's own compiled function,
    a function already compiled, and a run without progress say nothing."""
    from numba import njit

    from cutfem.runs import runner

    def compiled(module):
        def f(x):
            return x + 1.0

        f.__module__ = module
        return njit(f)  # not cached: each call below with a new signature compiles

    ours, theirs = compiled("cutfem.probe"), compiled("my_lab.kernels")

    @register("test-compiles", levels=[1.0, 2.0], level_name="n")
    def level(n):
        theirs(n)  # a user's function first: no note
        ours(n)  # compiled at n = 1 (a float), already compiled at n = 2
        return {"h": 1.0 / n, "dofs": 1}

    monkeypatch.setattr(runner, "_COMPILE_ANNOUNCED", False)
    cutfem.run("test-compiles", progress=False)  # no progress: nothing said, and the note is still to come
    assert capsys.readouterr().err == "" and not runner._COMPILE_ANNOUNCED
    ours(1), theirs(1)  # compiled outside a run: nothing said
    ours(np.float32(1.0)), ours(np.int8(0))
    assert capsys.readouterr().err == "" and not runner._COMPILE_ANNOUNCED
    cutfem.run("test-compiles", progress=True, levels=[np.int8(2)])  # only the user's function compiles (for int8)
    assert runner.COMPILE_NOTE not in capsys.readouterr().err and not runner._COMPILE_ANNOUNCED
    cutfem.run("test-compiles", progress=True, levels=[np.uint16(3), 4.0])  # ours compiles for uint16 at the first level
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("[1/2] test-compiles n=3 ... (" + runner.COMPILE_NOTE + ") done in"), lines
    assert lines[1].startswith("[2/2] test-compiles n=4.0 ... done in"), lines
    ours(np.int32(5))  # a new compilation later in the process: said once only
    cutfem.run("test-compiles", progress=True, levels=[np.int16(6)])
    assert runner.COMPILE_NOTE not in capsys.readouterr().err
    from numba.core import event

    assert not event._registered["numba:compile"]  # the listener lives only while a run does


def test_failing_level_in_python_raises_unless_kept(monkeypatch):
    from cutfem.geometry.shapes import Torus

    calls = []

    def boom(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise FloatingPointError("level two broke")
        return orig(*a, **k)

    problem = cutfem.get_problem("mean-curvature-cut")
    orig = problem.solve_level
    monkeypatch.setattr(problem, "solve_level", boom)
    with pytest.raises(FloatingPointError):
        cutfem.run("mean-curvature-cut", levels=[0.2, 0.1, 0.05])
    calls.clear()
    res = cutfem.run("mean-curvature-cut", levels=[0.2, 0.1, 0.05], keep_finished=True)
    assert len(res.records) == 1 and res.failure == {"index": 1, "level": 0.1, "error_type": "FloatingPointError", "message": "level two broke"}
    assert isinstance(res.exception, FloatingPointError) and len(calls) == 2
    assert Torus  # the module of the problem is importable alongside


def test_git_commit_is_none_without_git(monkeypatch):
    import cutfem.runs.runner as runner

    def no_git(*a, **k):
        raise FileNotFoundError("git")

    monkeypatch.setattr(subprocess, "run", no_git)
    assert runner._git_state() == {"git_commit": None, "git_modified": None}

    @register("test-no-git", levels=[0.5], level_name="step")
    def level(step):
        return {"h": step, "toy_error": step}

    assert cutfem.run("test-no-git").to_json()["git_commit"] is None


def test_run_records_start_time_and_table_shows_wall_time(monkeypatch):
    import time as _time

    import cutfem.runs.runner as runner

    stamps = iter(["2026-01-01T00:00:00Z", "2026-01-01T00:00:09Z"])
    monkeypatch.setattr(runner, "_utc_now", lambda: next(stamps))

    @register("test-sleepy", levels=[0.5], level_name="step")
    def sleepy(step):
        _time.sleep(0.05)
        return {"h": step, "toy_error": step}

    res = cutfem.run("test-sleepy")
    assert res.created_utc == "2026-01-01T00:00:00Z"  # taken before the levels ran
    wall = res.records[0]["wall_time"]
    assert wall >= 0.05 and res.records[0]["time"] == {}
    assert res.table().splitlines()[2].split()[-1] == f"{wall:.2f}"


def test_a_level_without_h_fails_with_the_reason():
    @register("test-no-h", levels=[0.5])
    def no_h(level):
        return {"dofs": 3}

    with pytest.raises(TypeError, match="without the key h"):
        cutfem.run("test-no-h")


def test_rates_skip_non_finite_errors_and_count_numpy_scalars():
    """An infinite error (a diverged level) has no rate instead of crashing the run with
    math.log(0); a NaN error has no rate (None in memory as in the JSON); an error held in a
    numpy float32 is an error key like any float (table, rates), a bool is not."""

    @register("test-odd-errors", levels=[1, 2, 4, 8], level_name="n", level_type=int)
    def odd(n):
        return {"h": 1.0 / n, "inf_error": float("inf") if n == 2 else 1.0 / n, "nan_error": float("nan") if n == 4 else n**-2.0,
                "f32_error": np.float32(n**-3.0), "flag_error": True}

    res = cutfem.run("test-odd-errors")
    assert res.error_keys() == ["inf_error", "nan_error", "f32_error"]
    assert res.rates["inf_error"][:2] == [None, None] and res.rates["inf_error"][2] == pytest.approx(1.0)
    assert res.rates["nan_error"][0] == pytest.approx(2.0) and res.rates["nan_error"][1:] == [None, None]
    assert res.rates["f32_error"] == pytest.approx([3.0, 3.0, 3.0])
    data = json.loads(res.dumps())
    assert data["rates"]["nan_error"][1:] == [None, None] and data["records"][2]["nan_error"] is None
    # level 4 (blank cells drop out of split): inf_error 1/4 without a rate, nan_error nan without one, f32_error 1/64, rate 3
    assert res.table().splitlines()[4].split()[:6] == ["4", "0.25", "2.5000e-01", "nan", "1.5625e-02", "3.00"]


def test_table_shows_the_size_of_the_domain_its_records_have():
    """The table's size column is the records' area (a surface) or volume (a bulk domain), left out
    when no record has either (a blank 'area' column stood beside every bulk run)."""

    @register("test-bulk-sizes", levels=[1, 2], level_name="n", level_type=int)
    def bulk(n):
        return {"h": 1.0 / n, "l2_error": n**-2.0, "volume": 4.0 + 0.1 / n}

    @register("test-no-sizes", levels=[1], level_name="n", level_type=int)
    def plain(n):
        return {"h": 1.0, "l2_error": 1.0}

    lines = cutfem.run("test-bulk-sizes").table().splitlines()
    assert lines[0].split() == ["level", "h", "dofs", "l2_error", "rate", "volume", "time[s]"]
    assert lines[3].split()[:5] == ["2", "0.5", "2.5000e-01", "2.00", "4.050000"]  # no dofs: blank
    assert cutfem.run("test-no-sizes").table().splitlines()[0].split() == ["level", "h", "dofs", "l2_error", "rate", "time[s]"]


def test_json_of_a_record_with_numpy_values():
    """numpy scalars and arrays in a record are written as the JSON numbers and booleans they hold
    (a numpy bool was the string "np.True_"), NaN and infinity as null: strict JSON."""

    @register("test-numpy-record", levels=[0.5], level_name="step")
    def numpy_record(step):
        return {"h": step, "converged": np.bool_(True), "flags": np.array([True, False]), "n": np.int8(3),
                "x_error": np.float32(0.25), "spread": np.array([1.5, np.nan, -np.inf])}

    text = cutfem.run("test-numpy-record").dumps()
    rec = json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in the JSON"))["records"][0]
    assert rec["converged"] is True and rec["flags"] == [True, False] and rec["n"] == 3
    assert rec["x_error"] == 0.25 and rec["spread"] == [1.5, None, None]
