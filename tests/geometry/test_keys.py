"""Tests for cutfem.geometry.keys: integer keys, their radix sort, grouping and distinct values,
against numpy's sorts and uniques."""

import numpy as np
import pytest


def test_stable_argsort_is_the_stable_argsort():
    """The radix argsort equals np.argsort(kind="stable") for narrow and wide keys (one and
    several radix passes), negative keys, many ties, and other integer dtypes."""
    from cutfem.geometry.keys import stable_argsort

    rng = np.random.default_rng(7)
    for trial in range(120):
        n = int(rng.integers(0, 5000))
        bits = int(rng.integers(1, 63))
        keys = rng.integers(0, 2**bits, n, dtype=np.int64)
        if trial % 3 == 0:
            keys %= max(1, n // 4)  # ties
        if trial % 5 == 0:
            keys -= 2 ** (bits - 1)  # negative keys
        for dtype in (np.int64, np.int32, np.uint16):
            k = keys.astype(dtype) if dtype is np.int64 or bits < 15 else keys
            np.testing.assert_array_equal(stable_argsort(k), np.argsort(k, kind="stable"))


def test_dense_unique_is_unique():
    from cutfem.geometry.keys import dense_unique

    rng = np.random.default_rng(3)
    ids = rng.integers(0, 1000, (300, 4))
    u, inv = dense_unique(ids, 1000)
    eu, einv = np.unique(ids, return_inverse=True)
    np.testing.assert_array_equal(u, eu)
    np.testing.assert_array_equal(inv, einv.reshape(ids.shape))
    assert inv.dtype == np.int32
    u64, inv64 = dense_unique(ids, 1000, np.int64)
    assert inv64.dtype == np.int64
    np.testing.assert_array_equal(u64, u)
    np.testing.assert_array_equal(inv64, inv)
    with pytest.raises(ValueError, match="cannot hold"):
        dense_unique(ids, 1000, np.int8)


@pytest.mark.parametrize("base", [2**21 - 3, 2**22 + 5, 20_000_000, 2**31 + 7])
def test_face_keys_group_faces_with_large_node_ids(base):
    """Faces of tets whose node ids lie above 2**21 and 2**22 (a single int64 of three ids would
    overflow there) and at 20 million are grouped exactly: the two tets sharing a face pair up, the
    others stay alone, and the sorted columns are the face's node ids."""
    from cutfem.geometry.keys import pair_up, tet_face_keys

    n = base + 10
    # two tets sharing the face {base, base+1, base+2}, listed in different orders, and one apart
    tets = np.array([[base, base + 1, base + 2, base + 3], [base + 4, base + 2, base, base + 1], [base + 5, base + 6, base + 7, base + 9]])
    keys = tet_face_keys(tets, n)
    assert len(keys) == 3 and all(col.shape == (12,) for col in keys)
    rows = np.stack(keys, axis=1)
    np.testing.assert_array_equal(rows, np.sort(tets[:, None, :].repeat(4, 1)[:, np.arange(4)[:, None], [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1))
    order, starts, counts = pair_up(keys)
    assert counts.sum() == 12 and len(counts) == 11  # 12 face rows, one face shared
    shared = np.flatnonzero(counts == 2)
    assert shared.size == 1
    pair = np.sort(order[starts[shared[0]] : starts[shared[0]] + 2])
    np.testing.assert_array_equal(pair, [3, 4])  # face opposite local vertex 3 of tet 0 and vertex 0 of tet 1
    np.testing.assert_array_equal(rows[pair[0]], [base, base + 1, base + 2])
    # the groups come in lexicographic order of the rows
    firsts = rows[order[starts]]
    assert np.all(np.diff(firsts[:, 0]) >= 0)
    np.testing.assert_array_equal(np.lexsort(firsts.T[::-1]), np.arange(len(firsts)))


def test_sorted_row_keys_pairs_with_large_ids():
    from cutfem.geometry.keys import sorted_row_keys

    n = 20_000_001
    rows = np.array([[n - 1, 2**22 + 1], [2**22 + 1, n - 1], [3, 2**21 + 9]])
    k = sorted_row_keys(rows, n)
    assert k[0] == k[1] == (2**22 + 1) * n + n - 1 and k[2] == 3 * n + 2**21 + 9
    with pytest.raises(ValueError, match="tet_face_keys"):
        sorted_row_keys(np.zeros((2, 3), int), 10)


def test_stable_argsort_of_columns_is_the_lexsort():
    """Column tuples (mixed dtypes, negative values, widths summing past 63 bits) sort as np.lexsort."""
    from cutfem.geometry.keys import stable_argsort

    rng = np.random.default_rng(11)
    for trial in range(40):
        n = int(rng.integers(0, 3000))
        cols = []
        for j in range(int(rng.integers(1, 4))):
            bits = int(rng.integers(1, 40))
            c = rng.integers(0, 2**bits, n, dtype=np.int64)
            if trial % 3 == 0:
                c %= 3  # ties
            if trial % 4 == j:
                c -= 2 ** (bits - 1)
            cols.append(c.astype(np.int32) if bits < 31 and trial % 2 else c)
        np.testing.assert_array_equal(stable_argsort(tuple(cols)), np.lexsort(cols[::-1]))
