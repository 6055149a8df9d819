"""The allocation settings applied on import (cutfem.memory)."""

import json
import os
import platform
import subprocess
import sys

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
