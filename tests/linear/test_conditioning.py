"""The conditioning of a fit against numpy's SVD of the whole column-scaled design
[A, level columns], written out densely (the way no fit computes it any more)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hamid.linear import solve
from hamid.linear.design import Block


def _dense(blocks: list[Block], J: int) -> np.ndarray:
    """The weighted design with one indicator column per trajectory's level, columns
    scaled to unit norm, those of trajectories without level rows left out."""
    parts = []
    for block in blocks:
        sw = np.sqrt(block.weight)
        levels = np.zeros((block.n_rows, J))
        if block.has_level:
            levels[np.arange(block.n_rows), block.group] = sw
        parts.append(np.hstack([block.A * sw[:, None], levels]))
    design = np.vstack(parts)
    norms = np.linalg.norm(design, axis=0)
    return design[:, norms > 0] / norms[norms > 0]


def _blocks(seed: int, J: int, p: int, sizes: list[int], weak_rows: int,
            collinear: float) -> list[Block]:
    rng = np.random.default_rng(seed)
    group = np.repeat(np.arange(len(sizes)), sizes)
    n = len(group)
    A = rng.standard_normal((n, p)) + rng.standard_normal(p)   # columns with a mean
    A[:, -1] = A[:, 0] + collinear * A[:, -1]                  # nearly collinear pair
    A += 3 * rng.standard_normal((J, p))[group]                # levels that move A
    blocks = [Block("energy", A, rng.standard_normal(n), group, np.arange(n, dtype=float),
                    rng.uniform(0.5, 2.0, n), True)]
    if weak_rows:
        blocks.append(Block("weak", rng.standard_normal((weak_rows, p)),
                            rng.standard_normal(weak_rows), rng.integers(0, J, weak_rows),
                            np.arange(weak_rows, dtype=float), np.ones(weak_rows), False))
    return blocks


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), p=st.integers(1, 5), J=st.integers(1, 12),
       weak_rows=st.sampled_from([0, 40]), collinear=st.sampled_from([1.0, 1e-3, 1e-6]),
       short=st.integers(0, 3))
def test_singular_values_and_weakest_direction_equal_the_dense_svd(
        seed, p, J, weak_rows, collinear, short):
    # `short` trajectories at the end have no level rows (too short for a window)
    with_rows = max(J - short, 1)
    sizes = list(np.random.default_rng(seed).integers(p + 2, 30, with_rows))
    blocks = _blocks(seed, J, p, sizes, weak_rows, collinear)
    names = [f"c{k}" for k in range(p)]
    labels = list(range(J))
    cond = solve.conditioning(blocks, names, labels)
    _, s, Vt = np.linalg.svd(_dense(blocks, J), full_matrices=False)
    np.testing.assert_allclose(cond.singular_values, s, rtol=1e-9, atol=1e-12 * s[0])
    assert cond.condition_number == pytest.approx(s[0] / s[-1], rel=1e-8)
    gap = s[-2] - s[-1] if len(s) > 1 else 1.0
    if gap > 1e-6 * s[0]:   # a unique weakest direction: the same, up to its sign
        used = [*names, *(f"h[{j}]" for j in range(with_rows))]
        weakest = dict(zip(used, Vt[-1], strict=True))
        shown = {name for name, w in weakest.items() if name in names or abs(w) >= 0.05}
        assert set(cond.weakest_direction) == shown
        found = np.array([cond.weakest_direction[name] for name in sorted(shown)])
        expected = np.array([weakest[name] for name in sorted(shown)])
        sign = np.sign(found @ expected)
        np.testing.assert_allclose(found, sign * expected, atol=1e-7)


def test_many_trajectories_take_no_dense_matrix_of_all_levels():
    """10,000 trajectories: the dense design would be 2 GB; the factor's way is small."""
    J, p = 10_000, 3
    blocks = _blocks(0, J, p, [6] * J, 0, 1.0)
    cond = solve.conditioning(blocks, [f"c{k}" for k in range(p)], list(range(J)))
    assert len(cond.singular_values) == p + J
    # all but 2p singular values belong to level combinations the parameters do not see
    assert np.sum(np.isclose(cond.singular_values, 1.0, rtol=0, atol=1e-12)) >= J - p
    assert np.isfinite(cond.condition_number)
