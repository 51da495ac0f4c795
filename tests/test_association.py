"""Gated Hungarian association against hand-worked cost matrices."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fusion_server.association import associate


def as_pairs(matches):
    return [tuple(int(v) for v in m) for m in matches]


def test_square_matrix_picks_the_cheapest_permutation():
    # Greedy would take (0, 0) = 1 and then be left with (1, 1) = 9: total 10.
    # The optimum is (0, 1) + (1, 0) = 2 + 3 = 5.
    cost = np.array([[1.0, 2.0], [3.0, 9.0]])
    m, ut, ud = associate(cost, gate=10.0)
    assert as_pairs(m) == [(0, 1), (1, 0)]
    assert ut.size == 0 and ud.size == 0


def test_pairs_above_the_gate_are_dropped():
    cost = np.array([[0.2, 5.0], [5.0, 0.7]])
    m, ut, ud = associate(cost, gate=0.5)
    assert as_pairs(m) == [(0, 0)]
    assert ut.tolist() == [1] and ud.tolist() == [1]


def test_gate_is_inclusive():
    m, _, _ = associate(np.array([[0.5]]), gate=0.5)
    assert as_pairs(m) == [(0, 0)]


def test_gating_prefers_more_admissible_matches():
    # Track 0 is nearest detection 0 (0.1) but track 1 can only take
    # detection 0 (0.3): two matches 0->1, 1->0 (0.4 + 0.3) beat one match.
    cost = np.array([[0.1, 0.4], [0.3, 2.0]])
    m, ut, ud = associate(cost, gate=0.5)
    assert as_pairs(m) == [(0, 1), (1, 0)]
    assert ut.size == 0 and ud.size == 0


def test_rectangular_more_detections_than_tracks():
    cost = np.array([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0]])
    # permutations: (0->1, 1->0) = 1 + 2 = 3; (0->2, 1->1) = 3 + 0 = 3; (0->0, 1->1) = 4;
    # ties are broken by the solver, so check the total and the leftovers.
    m, ut, ud = associate(cost, gate=10.0)
    assert len(m) == 2 and ut.size == 0 and len(ud) == 1
    assert cost[m[:, 0], m[:, 1]].sum() == pytest.approx(3.0)
    assert sorted(set(range(3)) - set(m[:, 1].tolist())) == ud.tolist()


def test_rectangular_more_tracks_than_detections():
    cost = np.array([[0.3], [0.2], [0.9]])
    m, ut, ud = associate(cost, gate=1.0)
    assert as_pairs(m) == [(1, 0)]
    assert ut.tolist() == [0, 2] and ud.size == 0


def test_nan_and_inf_never_match():
    cost = np.array([[np.nan, 0.2], [np.inf, np.inf]])
    m, ut, ud = associate(cost, gate=np.inf)
    assert as_pairs(m) == [(0, 1)]
    assert ut.tolist() == [1] and ud.tolist() == [0]


def test_empty_inputs():
    for shape in [(0, 0), (0, 3), (2, 0)]:
        m, ut, ud = associate(np.zeros(shape), gate=1.0)
        assert m.shape == (0, 2)
        assert ut.tolist() == list(range(shape[0])) and ud.tolist() == list(range(shape[1]))


def test_all_gated():
    m, ut, ud = associate(np.full((2, 2), 3.0), gate=1.0)
    assert m.shape == (0, 2) and ut.tolist() == [0, 1] and ud.tolist() == [0, 1]


def test_input_is_not_modified():
    cost = np.array([[0.1, 9.0], [9.0, 0.2]])
    before = cost.copy()
    associate(cost, gate=1.0)
    assert np.array_equal(cost, before)


def test_matches_brute_force_on_random_matrices():
    rng = np.random.default_rng(3)
    for _ in range(200):
        t, d = (int(v) for v in rng.integers(1, 5, size=2))
        cost = rng.uniform(0.0, 2.0, size=(t, d)).round(2)
        gate = 1.0
        m, ut, ud = associate(cost, gate)
        # Oracle: the most admissible pairs, then the least total cost.
        best = None
        for perm in itertools.permutations(range(max(t, d)), min(t, d)):
            pairs = [(r, c) for r, c in (zip(range(t), perm) if t <= d else zip(perm, range(d)))]
            ok = [(r, c) for r, c in pairs if cost[r, c] <= gate]
            key = (-len(ok), round(sum(cost[r, c] for r, c in ok), 9))
            best = key if best is None or key < best else best
        got = (-len(m), round(float(cost[m[:, 0], m[:, 1]].sum()), 9)) if len(m) else (0, 0.0)
        assert got == best
        assert np.all(cost[m[:, 0], m[:, 1]] <= gate)
        assert len(m) + len(ut) == t and len(m) + len(ud) == d


@pytest.mark.parametrize("gate", [float("nan"), float("-inf")])
def test_bad_gate(gate):
    with pytest.raises(ValueError, match="gate"):
        associate(np.zeros((1, 1)), gate)


def test_bad_shape():
    with pytest.raises(ValueError, match="cost"):
        associate(np.zeros(3), 1.0)
