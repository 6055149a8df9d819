"""The allocation settings applied on import (cutfem.memory)."""

import json
import os
import platform
import subprocess
import sys

import numpy as np
import pytest

from cutfem.memory import thp_defrag_mode

LINUX_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


def _settings_in_fresh_process(**env):
    code = (
        "import json, cutfem, cutfem.memory as m\n"
        "get, _ = m._numpy_hugepage_functions()\n"
        "print(json.dumps(dict(m.SETTINGS, numpy_now=None if get is None else bool(get()))))\n"
    )
    full = {k: v for k, v in os.environ.items() if k not in ("CUTFEM_ALLOCATOR", "NUMPY_MADVISE_HUGEPAGE")}
    full.update(env)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not LINUX_GLIBC, reason="the glibc thresholds exist on Linux with glibc only")
def test_import_sets_thresholds_and_hugepage_advice():
    s = _settings_in_fresh_process()
    assert s["malloc"] is True
    if s["thp_defrag"] in ("always", "madvise", "defer+madvise"):
        assert s["numpy_hugepage"] is False and s["numpy_now"] is False
    else:
        assert s["numpy_hugepage"] == s["numpy_now"]


def test_opt_out_leaves_the_process_alone():
    s = _settings_in_fresh_process(CUTFEM_ALLOCATOR="system")
    assert s["skipped"] == "CUTFEM_ALLOCATOR=system" and s["malloc"] is False
    assert s["numpy_hugepage"] is None


def test_users_numpy_hugepage_choice_is_respected():
    s = _settings_in_fresh_process(NUMPY_MADVISE_HUGEPAGE="1")
    assert s["numpy_now"] is True and s["numpy_hugepage"] is True


def test_thp_defrag_mode_reads_the_bracketed_choice(tmp_path):
    f = tmp_path / "defrag"
    f.write_text("always defer defer+madvise [madvise] never\n")
    assert thp_defrag_mode(str(f)) == "madvise"
    f.write_text("no brackets\n")
    assert thp_defrag_mode(str(f)) is None
    assert thp_defrag_mode(str(tmp_path / "missing")) is None


# ----------------------------------------------------------------------------------------------
# estimates checked before large allocations
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text,value", [("2000", 2000), ("1.5GiB", 3 * 2**29), ("500M", 500 * 2**20), ("2 gb", 2 * 10**9), ("1TiB", 2**40)])
def test_memory_limit_variable_is_read(monkeypatch, text, value):
    from cutfem.memory import available_memory

    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", text)
    assert available_memory() == (value, "CUTFEM_MEMORY_LIMIT")


@pytest.mark.parametrize("text", ["lots", "-1G", "0", "3 parsecs", "inf"])
def test_bad_memory_limit_is_refused(monkeypatch, text):
    from cutfem.memory import available_memory

    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", text)
    with pytest.raises(ValueError, match="is not a memory size; write e.g. 8GiB"):
        available_memory()


def test_available_memory_without_limit_is_the_kernels(monkeypatch):
    from cutfem.memory import available_memory

    monkeypatch.delenv("CUTFEM_MEMORY_LIMIT", raising=False)
    value, source = available_memory()
    assert source in ("MemAvailable", "SC_AVPHYS_PAGES", "SC_PHYS_PAGES")
    assert 2**24 < value <= os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def test_check_memory_states_estimate_available_and_fix(monkeypatch):
    from cutfem.memory import InsufficientMemoryError, check_memory

    monkeypatch.setenv("CUTFEM_MEMORY_LIMIT", "1GiB")
    check_memory(2**30, "exactly the limit", "nothing")  # not above: accepted
    with pytest.raises(InsufficientMemoryError, match=r"^the thing needs about 1.5 GiB of memory, more than the 1 GiB available \(CUTFEM_MEMORY_LIMIT\); do less$"):
        check_memory(1.5 * 2**30, "the thing", "do less")
    assert issubclass(InsufficientMemoryError, MemoryError)


@pytest.mark.slow
def test_cut_torus_beyond_two_million_active_nodes():
    """The cut torus at spacing 0.0042 (about 2.6 million active nodes: past 2**21, where the old
    single-integer face key overflowed) through the cut and the face topology: each interior face is
    a face of both its (distinct) tets, and there are at most 2 T of them.  Peak about 6 GiB."""
    from cutfem.cut import cut_mesh
    from cutfem.levelset import Torus
    from cutfem.memory import available_memory
    from cutfem.mesh import structured_box

    if available_memory()[0] < 12 * 2**30:
        pytest.skip("needs about 8 GiB free (the cut estimate at this spacing is 5.7 GiB)")
    cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.0042), Torus(1.0, 0.5))
    assert cut.n_nodes > 2**21
    faces, face_tets = cut.interior_faces, cut.interior_face_tets
    F = len(faces)
    # an interior face takes two of the 4 T face slots; the thin band has many boundary faces
    # (F / T = 1.66 at this spacing)
    assert 1.5 * cut.n_tets < F <= 2 * cut.n_tets
    assert np.all(face_tets[:, 0] != face_tets[:, 1])
    # each interior face is a face of both its tets
    sample = np.random.default_rng(0).choice(F, 20000, replace=False)
    for side in range(2):
        tets = cut.tets[face_tets[sample, side]]
        for col in range(3):
            assert np.all(np.any(tets == faces[sample, col, None], axis=1))
    assert abs(cut.area - 4 * np.pi**2 * 0.5) < 1e-3
