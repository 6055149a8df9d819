"""Library manners: importing cutfem changes nothing process-wide; the command line opts into the
allocation settings of cutfem.memory.  Each check runs in a fresh interpreter, so that what it sees
is what one import (or one command) did, not what earlier tests left behind."""

import json
import os
import platform
import subprocess
import sys

import pytest

from cutfem.memory import thp_defrag_mode

LINUX_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
STALLING = ("always", "madvise", "defer+madvise")


def _fresh_process(code: str, **env) -> dict:
    """Run ``code`` in a new interpreter (the user's allocator and matplotlib variables removed,
    ``env`` added) and return the JSON object it prints last."""
    full = {k: v for k, v in os.environ.items() if k not in ("CUTFEM_ALLOCATOR", "NUMPY_MADVISE_HUGEPAGE", "MPLBACKEND")}
    full.update(env)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


_HUGEPAGE_GETTER = (
    "import numpy\n"
    "try:\n"
    "    from numpy._core.multiarray import _get_madvise_hugepage as get_hp\n"
    "except ImportError:\n"
    "    from numpy.core.multiarray import _get_madvise_hugepage as get_hp\n"
)


def test_import_changes_nothing_process_wide(tmp_path):
    """numpy's huge-page advice, the matplotlib backend and pyplot are as before the import, also
    after registering the problems and drawing a convergence plot and a study figure."""
    code = _HUGEPAGE_GETTER + (
        "import json, matplotlib, sys\n"
        "matplotlib.use('svg')\n"
        "before = {'hugepage': bool(get_hp()), 'backend': matplotlib.get_backend()}\n"
        "import cutfem, cutfem.memory\n"
        "from cutfem.registry import RunResult\n"
        "problems = sorted(cutfem.available_problems())\n"
        "from cutfem.convergence import convergence_plot\n"
        "rec = [{'h': 0.2, 'l2_error': 0.1}, {'h': 0.1, 'l2_error': 0.026}]\n"
        f"convergence_plot(RunResult('p', {{}}, [0.2, 0.1], rec), {str(tmp_path / 'conv.png')!r})\n"
        "from cutfem.convergence import new_figure\n"
        "from cutfem.studies.common import save_figure\n"
        "fig, ax = new_figure(3, 2)\n"
        "ax.plot([0, 1], [1, 0])\n"
        f"save_figure(fig, {str(tmp_path)!r}, 'study')\n"
        "after = {'hugepage': bool(get_hp()), 'backend': matplotlib.get_backend()}\n"
        "print(json.dumps({'before': before, 'after': after, 'settings': cutfem.memory.SETTINGS, 'problems': problems,\n"
        "                  'pyplot': 'matplotlib.pyplot' in sys.modules}))\n"
    )
    s = _fresh_process(code)
    assert s["after"] == s["before"] and s["before"]["backend"] == "svg"
    assert s["settings"] == {}, "importing cutfem must not apply cutfem.memory.configure()"
    assert not s["pyplot"], "the library draws without pyplot"
    assert "mean-curvature-cut" in s["problems"]
    assert (tmp_path / "conv.png").stat().st_size > 1000
    assert (tmp_path / "study.png").stat().st_size > 1000 and (tmp_path / "study.pdf").stat().st_size > 1000


def _after_command(argv, **env) -> dict:
    code = _HUGEPAGE_GETTER + (
        "import contextlib, io, json\n"
        "import cutfem.cli, cutfem.memory\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    status = cutfem.cli.main({argv!r})\n"
        "print(json.dumps(dict(cutfem.memory.SETTINGS, status=status, numpy_now=bool(get_hp()))))\n"
    )
    return _fresh_process(code, **env)


@pytest.mark.skipif(not LINUX_GLIBC, reason="the glibc thresholds exist on Linux with glibc only")
def test_the_command_line_configures():
    s = _after_command(["list"])
    assert s["status"] == 0
    assert s["malloc"] is True and "skipped" not in s
    if s["thp_defrag"] in STALLING:
        assert s["numpy_hugepage"] is False and s["numpy_now"] is False
    else:
        assert s["numpy_hugepage"] == s["numpy_now"]


def test_the_command_line_respects_the_opt_out():
    s = _after_command(["list"], CUTFEM_ALLOCATOR="system")
    assert s["status"] == 0
    assert s["skipped"] == "CUTFEM_ALLOCATOR=system" and s["malloc"] is False and s["numpy_hugepage"] is None


def test_users_numpy_hugepage_choice_is_respected():
    s = _after_command(["list"], NUMPY_MADVISE_HUGEPAGE="1")
    assert s["numpy_now"] is True and s["numpy_hugepage"] is True


def test_study_command_lines_configure(tmp_path):
    """A study's ``main`` (python -m cutfem.studies.NAME) applies the settings before running."""
    code = (
        "import json\n"
        "import cutfem.memory\n"
        "from cutfem.studies.common import study_main\n"
        "seen = {}\n"
        "def run(out, size, progress):\n"
        "    seen.update(settings=dict(cutfem.memory.SETTINGS), size=size)\n"
        f"study_main(run, 'probe')(['--out', {str(tmp_path)!r}, '--tiny', '--quiet'])\n"
        "print(json.dumps(seen))\n"
    )
    s = _fresh_process(code, CUTFEM_ALLOCATOR="system")
    assert s["size"] == "tiny" and s["settings"]["skipped"] == "CUTFEM_ALLOCATOR=system"


def test_thp_defrag_mode_reads_the_bracketed_choice(tmp_path):
    f = tmp_path / "defrag"
    f.write_text("always defer defer+madvise [madvise] never\n")
    assert thp_defrag_mode(str(f)) == "madvise"
    f.write_text("no brackets\n")
    assert thp_defrag_mode(str(f)) is None
    assert thp_defrag_mode(str(tmp_path / "missing")) is None
