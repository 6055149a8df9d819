"""Background meshes at the edges of the API (issue 45, items 2b, 2c, 2g and part 4): meshes that
are tangled or overlap, boxes whose spacing contradicts their corners or whose sizes pass int64,
spacings so small that counts overflow, empty meshes and unmerged STL soups."""

import re

import meshio
import numpy as np
import pytest

from cutfem.cli import main
from cutfem.memory import InsufficientMemoryError
from cutfem.mesh import StructuredBox, TetMesh, read_mesh, structured_box, write_mesh

# -- 2c: a spacing that contradicts the corners and the cells -------------------------------------


def test_structured_box_refuses_a_spacing_that_does_not_match_its_corners():
    # 10 cells of 0.2 reach 2.0, not the upper corner 1.0: the box used to report bounds [0, 1]^3
    # while its nodes reached 2.0
    with pytest.raises(ValueError, match=r"spacing=\[0\.2, 0\.2, 0\.2\] does not match the corners and cells.*"
                                         r"lower \+ cells \* spacing = \[2\.0, 2\.0, 2\.0\].*"
                                         r"consistent spacing is \(upper - lower\) / cells = \[0\.1, 0\.1, 0\.1\]"):
        StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.2)


def test_structured_box_accepts_a_spacing_that_matches_to_round_off():
    box = StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.1)
    assert box.points.max() == pytest.approx(1.0, abs=1e-15)
    # a box far from the origin: (upper - lower) / cells carries the corners' round-off
    far = structured_box([1e8] * 3, [1e8 + 1] * 3, spacing=0.001)
    assert far.spacing.tolist() == [0.001] * 3 and far.cells.tolist() == [1000] * 3
    StructuredBox([0] * 3, [1] * 3, [10] * 3, spacing=0.1 * (1 + 1e-12))


# -- 2g and part 4: sizes past int64, spacings that overflow the cell counts -----------------------


def test_cells_past_int64_are_refused_with_the_real_counts():
    # (3e6 + 1)**3 nodes used to wrap in int64 and be reported as 8.55e18
    with pytest.raises(InsufficientMemoryError, match=r"3,000,000 x 3,000,000 x 3,000,000 cells has 2\.70e\+19 nodes "
                                                      r"and 1\.62e\+20 tets: their ids do not fit in 64-bit integers.*"
                                                      r"6\.75e\+18 bytes.*give fewer cells"):
        structured_box([0] * 3, [1] * 3, cells=3_000_000)
    with pytest.raises(InsufficientMemoryError, match=r"1\.00e\+19 x .* cells has 1\.00e\+57 nodes"):
        structured_box([0] * 3, [1] * 3, cells=1e19)


def test_sizes_below_int64_are_exact_python_integers():
    box = structured_box([0] * 3, [1] * 3, cells=1_000_000)  # 6e18 tets: the ids still fit
    assert box.n_points == 1_000_001**3 and box.n_tets == 6 * 10**18
    assert isinstance(box.n_points, int) and isinstance(box.n_cells, int)


@pytest.mark.parametrize("spacing, nodes", [(1e-300, r"9\.99e\+899"), (1e-320, r"1\.00e\+960")])
def test_tiny_spacings_state_the_real_counts(spacing, nodes):
    # the cell counts overflowed to -9223372036854775808 ("need at least one cell per axis")
    with pytest.raises(InsufficientMemoryError) as err:
        structured_box([0] * 3, [1] * 3, spacing=spacing)
    text = str(err.value)
    assert re.search(rf"at spacing=1e-3[02]0 has {nodes} nodes", text), text
    assert "use a coarser spacing: at least 8.66e-07 for the ids to fit" in text
    assert "-9223372036854775808" not in text


def test_coordinates_near_1e30_state_the_real_counts():
    with pytest.raises(InsufficientMemoryError, match=r"at spacing=0\.1 has 7\.99e\+93 nodes.*at least 1\.73e\+24"):
        structured_box([-1e30] * 3, [1e30] * 3, spacing=0.1)


@pytest.mark.parametrize("argv", [["run", "poisson-cut", "--levels", "1e-320"],
                                  ["run", "mean-curvature-cut", "--spacing", "1e-320"]])
def test_cli_tiny_spacing_is_one_clear_line_and_exit_2(argv, capsys):
    assert main(argv + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "-9223372036854775808" not in err and "upper > lower" not in err
    assert re.search(r"spacing=1e-320 has 1\.\d\de\+961 nodes.*use a coarser spacing", err), err
