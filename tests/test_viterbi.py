"""Viterbi decoders: the batch path against a search over every path, the
fixed-lag decoder against the batch path, and commitments that never change."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fusion_server.viterbi import FixedLagViterbi, path_score, viterbi


def _random_model(rng: np.random.Generator, n_states: int, n_frames: int, per_step: bool):
    init = np.log(rng.dirichlet(np.ones(n_states)))
    shape = (n_frames - 1, n_states, n_states) if per_step else (n_states, n_states)
    trans = np.log(rng.dirichlet(np.ones(n_states), size=shape[:-1]))
    lik = rng.normal(0.0, 2.0, size=(n_frames, n_states))
    return init, trans, lik


def _brute_force(init, trans, lik):
    best, best_path = -np.inf, None
    for path in itertools.product(range(len(init)), repeat=len(lik)):
        s = path_score(init, trans, lik, np.array(path))
        if s > best:
            best, best_path = s, path
    return np.array(best_path), best


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("per_step", [False, True])
def test_batch_path_is_the_best_of_all_paths(seed, per_step):
    rng = np.random.default_rng(seed)
    n_states, n_frames = int(rng.integers(2, 5)), int(rng.integers(1, 7))
    init, trans, lik = _random_model(rng, n_states, n_frames, per_step)
    path, score = viterbi(init, trans, lik)
    want_path, want_score = _brute_force(init, trans, lik)
    assert path.tolist() == want_path.tolist()
    assert score == pytest.approx(want_score, abs=1e-9)
    assert path_score(init, trans, lik, path) == pytest.approx(score, abs=1e-9)


def test_forbidden_states_and_transitions_are_never_used():
    # state 2 is impossible in frame 1, and 0 -> 1 is forbidden
    init = np.log([0.5, 0.25, 0.25])
    with np.errstate(divide="ignore"):
        trans = np.log(np.array([[0.5, 0.0, 0.5], [0.3, 0.4, 0.3], [0.2, 0.6, 0.2]]))
    lik = np.array([[0.0, -5.0, -5.0], [-1.0, -1.0, -np.inf], [-9.0, 0.0, -9.0]])
    path, score = viterbi(init, trans, lik)
    want, want_score = _brute_force(init, trans, lik)
    assert path.tolist() == want.tolist()
    assert score == pytest.approx(want_score)
    assert path[1] != 2 and not (path[1] == 0 and path[2] == 1)


def test_empty_sequence():
    path, score = viterbi(np.zeros(3), np.zeros((3, 3)), np.zeros((0, 3)))
    assert path.shape == (0,) and score == 0.0


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="log_lik"):
        viterbi(np.zeros(3), np.zeros((3, 3)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="log_trans"):
        viterbi(np.zeros(3), np.zeros((2, 3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="log_init"):
        FixedLagViterbi(np.full(3, -np.inf))
    dec = FixedLagViterbi(np.zeros(2))
    dec.push(np.zeros(2))
    with pytest.raises(ValueError, match="log_trans"):
        dec.push(np.zeros(2))
    with pytest.raises(ValueError, match="keep"):
        dec.commit(-1)


@pytest.mark.parametrize("seed", range(6))
def test_fixed_lag_with_lag_covering_the_sequence_equals_batch(seed):
    rng = np.random.default_rng(100 + seed)
    n_states, n_frames = 4, 40
    init, trans, lik = _random_model(rng, n_states, n_frames, per_step=True)
    dec = FixedLagViterbi(init)
    for t in range(n_frames):
        dec.push(lik[t], trans[t - 1] if t else None)
        assert dec.commit(keep=n_frames) == []
    committed = dec.commit(keep=0)
    assert committed == viterbi(init, trans, lik)[0].tolist()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("lag", [0, 1, 3, 8])
def test_committed_states_never_change_and_come_within_the_lag(seed, lag):
    rng = np.random.default_rng(200 + seed)
    n_states, n_frames = 3, 60
    init, trans, lik = _random_model(rng, n_states, n_frames, per_step=False)
    dec = FixedLagViterbi(init)
    committed: list[int] = []
    for t in range(n_frames):
        dec.push(lik[t], trans if t else None)
        before = list(committed)
        committed += dec.commit(keep=lag)
        assert committed[: len(before)] == before
        # every frame older than the lag is committed
        assert len(committed) == max(0, t + 1 - lag)
        assert dec.pending == min(lag, t + 1)
    committed += dec.commit(keep=0)
    assert len(committed) == n_frames
    # Each commit is the best path's state given the committed prefix: the
    # whole committed path scores no better than the batch optimum.
    best = viterbi(init, trans, lik)[1]
    assert path_score(init, trans, lik, np.array(committed)) <= best + 1e-9


def test_fixed_lag_equals_batch_when_the_evidence_is_clear():
    # Long runs with a clear margin: a lag longer than it takes the evidence to
    # outweigh a switch decides exactly as the batch decoder.
    n_states = 3
    truth = [0] * 20 + [1] * 15 + [2] * 25 + [0] * 10
    rng = np.random.default_rng(7)
    lik = rng.normal(0.0, 0.3, size=(len(truth), n_states))
    lik[np.arange(len(truth)), truth] += 2.0
    stay = np.log(0.95)
    trans = np.full((n_states, n_states), np.log(0.025))
    np.fill_diagonal(trans, stay)
    init = np.log(np.full(n_states, 1 / 3))
    dec = FixedLagViterbi(init)
    committed: list[int] = []
    for t in range(len(truth)):
        dec.push(lik[t], trans if t else None)
        committed += dec.commit(keep=5)
    committed += dec.commit(keep=0)
    assert committed == viterbi(init, trans, lik)[0].tolist() == truth


def test_a_short_detour_is_smoothed_away_but_a_lasting_change_is_taken():
    # Two frames that favour state 1 by 2 nats each cannot pay for two switches
    # of 3 nats; ten frames that do pay for one switch.
    switch = -3.0
    trans = np.array([[0.0, switch], [switch, 0.0]])
    init = np.zeros(2)
    frames = [[0.0, -2.0]] * 10 + [[-2.0, 0.0]] * 2 + [[0.0, -2.0]] * 10 + [[-2.0, 0.0]] * 10
    path = viterbi(init, trans, np.array(frames))[0].tolist()
    assert path == [0] * 22 + [1] * 10
