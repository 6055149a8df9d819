"""The performance benchmark's levels (cutfem.studies.performance_levels): the stages and sizes a
level records, its stage timer, and the fresh process each level runs in."""

import numpy as np
import pytest

from cutfem.studies import performance_levels


def test_levels_record_stages_sizes_and_errors():
    rec = performance_levels.cut_level(0.2)
    assert set(rec["time"]) == {"background", "cut", "topology", "matrix", "rhs", "solve", "errors"}
    assert rec["background_nodes"] == 17 * 17 * 7
    assert rec["active_tets"] > 0 and rec["interior_faces"] > rec["active_tets"] and rec["dofs"] > 0
    assert 0 < rec["l2_error"] < 2.0
    assert rec["total"] == pytest.approx(sum(rec["time"].values()))
    m = performance_levels.meshed_level(16, "flipped")
    assert m["dofs"] == 16 * 8 and m["triangles"] == 2 * 16 * 8
    assert set(m["time"]) == {"mesh", "matrix", "rhs", "solve", "errors"}


def test_stage_timer_keeps_cpu_and_faults_per_stage():
    """Per stage: the wall time, and user and system CPU time and minor page faults from getrusage.
    A stage that writes 64 MiB of a fresh anonymous mapping faults at least once per 2 MiB (once
    per 4 KiB page without transparent huge pages); a stage that only sleeps spends no CPU time."""
    import mmap
    import time

    t = performance_levels.StageTimer()
    region = mmap.mmap(-1, 64 * 2**20)  # fresh pages, not the allocator's reused heap
    with t("touch"):
        np.frombuffer(region, dtype=np.float64)[:] = 1.0
    with t("sleep"):
        time.sleep(0.05)
    with t("touch"):
        np.frombuffer(region, dtype=np.float64)[::512] += 1.0  # pages already there: no new faults needed
    assert set(t) == set(t.cpu) == {"touch", "sleep"}
    assert t["sleep"] >= 0.05 and t.cpu["sleep"]["user"] + t.cpu["sleep"]["system"] < 0.04
    assert t.cpu["touch"]["faults"] >= 64 // 2
    assert t.cpu["touch"]["user"] + t.cpu["touch"]["system"] <= 2 * t["touch"] + 0.02  # two cores at most
    assert np.frombuffer(region, dtype=np.float64)[512] == 2.0
    rec = performance_levels.cut_level(0.2)
    assert set(rec["stage_cpu"]) == set(rec["time"])


def test_peak_memory_is_the_level_process_own():
    """A parent that once held 0.4 GiB: the child's ru_maxrss would start there (Linux), its VmHWM does not."""
    import resource

    a = np.ones(50_000_000)
    a[1::512] = 2.0
    del a
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20 > 0.37
    rec = performance_levels.level_in_fresh_process("meshed-flipped", 16)
    assert 0.02 < rec["peak_memory_gib"] < 0.3
    assert "warm" in rec and "warm" not in performance_levels.level_in_fresh_process("meshed-flipped", 16, warm=False)  # --limit: once


def test_the_second_run_of_a_level_reuses_the_memory_of_the_first():
    """The objects of a level refer to each other, so the level process collects them before its
    second run: that run then takes its memory from the heap the first one freed, instead of
    touching fresh pages beside the first run's (about 1550 faults at spacing 0.05 without the
    collection, against about 20 thousand for the first run and a handful with it)."""
    rec = performance_levels.level_in_fresh_process("cut", 0.05)
    assert rec["page_faults"] > 5000
    assert 0 <= rec["warm"]["page_faults"] < rec["page_faults"] / 20
