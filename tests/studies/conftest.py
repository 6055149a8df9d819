"""The ngsxfem fixture of the comparisons with the peer (tests/studies/test_peers*.py): skips a test
when the optional peers are not installed (``pip install -e ".[peers]"``)."""

import pytest

REASON = 'ngsxfem comparison needs the optional peers: pip install -e ".[peers]" (ngsolve, xfem)'


def _importorskip(name):
    try:  # a broken binary install raises ImportError, not ModuleNotFoundError: skip on both
        return pytest.importorskip(name, reason=REASON, exc_type=ImportError)
    except TypeError:  # pytest < 8.2 has no exc_type (and skips on any ImportError)
        return pytest.importorskip(name, reason=REASON)


@pytest.fixture(scope="module")
def ngsxfem():
    _importorskip("ngsolve")
    return _importorskip("xfem")
