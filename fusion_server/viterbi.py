"""Most likely state paths of a discrete hidden Markov model, in the log domain.

The seed paper's event tracker (DESIGN.md, seed 002, section 3.1) finds each
person's best sequence of configurations -- outside, standing, fallen -- with
the Viterbi recursion

    psi_t(k) = log P(I_t | S_t = k) + max_l [ log P(S_t = k | S_{t-1} = l) + psi_{t-1}(l) ]

and a backtrack from the best final state. Two forms here:

* :func:`viterbi`: the batch decoder over a whole sequence.
* :class:`FixedLagViterbi`: the online decoder. Frames are pushed one at a
  time; :meth:`FixedLagViterbi.commit` decodes the frames not yet committed
  (the window since the last committed state, conditioned on it) and makes
  final all but the newest ``keep`` of them. A committed state never changes
  again, so decisions taken from committed states are never taken back, and
  a frame is committed at most ``keep`` frames after it arrived.

Ties between equally good predecessors or final states go to the lowest
state index, so both forms are deterministic. Pure math: no clock, no I/O.
"""

from __future__ import annotations

import numpy as np


def viterbi(
    log_init: np.ndarray, log_trans: np.ndarray, log_lik: np.ndarray
) -> tuple[np.ndarray, float]:
    """Best state path of a whole sequence and its log score.

    log_init: (S,) float64, log prior of the first frame's state.
    log_trans: (S, S) float64, ``log P(S_t = k | S_{t-1} = l)`` at ``[l, k]``,
        the same for every step; or (T - 1, S, S), one matrix per step
        (step ``t`` leads from frame ``t`` to frame ``t + 1``).
    log_lik: (T, S) float64, ``log P(I_t | S_t = k)``; ``-inf`` forbids a state.

    Returns ``(path, score)``: (T,) int64 state indices and the path's total
    log score ``log_init[path[0]] + sum log_trans + sum log_lik``. An empty
    sequence gives an empty path and score 0.
    """
    init, trans, lik = _checked(log_init, log_trans, log_lik)
    n = lik.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0.0
    delta = init + lik[0]
    back = np.zeros((n, lik.shape[1]), dtype=np.int64)
    for t in range(1, n):
        delta, back[t] = _step(delta, _trans_at(trans, t - 1), lik[t])
    path = _backtrack(back, int(np.argmax(delta)))
    return path, float(delta[path[-1]])


def path_score(log_init: np.ndarray, log_trans: np.ndarray, log_lik: np.ndarray, path: np.ndarray) -> float:
    """Log score of one given state path, as :func:`viterbi` counts it.

    path: (T,) state indices; shapes as for :func:`viterbi`."""
    init, trans, lik = _checked(log_init, log_trans, log_lik)
    p = np.asarray(path, dtype=np.int64)
    if p.shape != (lik.shape[0],):
        raise ValueError(f"path must have shape ({lik.shape[0]},), got {p.shape}")
    if len(p) == 0:
        return 0.0
    score = init[p[0]] + lik[np.arange(len(p)), p].sum()
    for t in range(1, len(p)):
        score += _trans_at(trans, t - 1)[p[t - 1], p[t]]
    return float(score)


class FixedLagViterbi:
    """Online Viterbi decoding with a bounded decision delay.

    log_init: (S,) float64, log prior of the first frame's state.

    Push each frame's (S,) log-likelihoods with :meth:`push` (and the (S, S)
    log transition matrix that leads to it from the previous frame; the first
    frame takes none). :meth:`commit` decodes the pending frames -- the window
    since the last committed state, starting from that state (or from the
    prior before anything is committed) -- and commits all but the newest
    ``keep``: their states on the window's best path become final and are
    returned, oldest first. When ``keep`` is at least the number of frames
    ever pushed, nothing commits until :meth:`commit` is called with
    ``keep=0``, and the states committed then are exactly :func:`viterbi`'s
    path over the whole sequence.

    pending: the frames pushed but not committed; tentative(): their states
    on the window's best path now (they may still change).
    """

    def __init__(self, log_init: np.ndarray) -> None:
        init = np.asarray(log_init, dtype=np.float64)
        if init.ndim != 1 or len(init) == 0 or np.isnan(init).any() or not np.isfinite(init.max()):
            raise ValueError("log_init must be a non-empty (S,) array with at least one finite entry and no NaN")
        self.log_init = init
        self.n_states = len(init)
        self._lik: list[np.ndarray] = []
        self._trans: list[np.ndarray | None] = []  # transition into each pending frame
        self._anchor: int | None = None  # the last committed state
        self.committed_count = 0

    @property
    def pending(self) -> int:
        return len(self._lik)

    @property
    def last_committed(self) -> int | None:
        """State of the newest committed frame, None before the first commit."""
        return self._anchor

    def push(self, log_lik: np.ndarray, log_trans: np.ndarray | None = None) -> None:
        """Add one frame: (S,) log-likelihoods and the (S, S) log transition
        matrix from the previous frame (ignored for the very first frame)."""
        lik = np.asarray(log_lik, dtype=np.float64)
        if lik.shape != (self.n_states,) or np.isnan(lik).any():
            raise ValueError(f"log_lik must be a ({self.n_states},) array without NaN, got shape {lik.shape}")
        first = self.committed_count == 0 and not self._lik
        trans = None
        if not first:
            if log_trans is None:
                raise ValueError("log_trans is required for every frame after the first")
            trans = np.asarray(log_trans, dtype=np.float64)
            if trans.shape != (self.n_states, self.n_states) or np.isnan(trans).any():
                raise ValueError(f"log_trans must be an ({self.n_states}, {self.n_states}) array without NaN")
        self._lik.append(lik)
        self._trans.append(trans)

    def tentative(self) -> np.ndarray:
        """(pending,) int64: the pending frames' states on the window's best path now."""
        return self._decode()

    def commit(self, keep: int) -> list[int]:
        """Commit every pending frame but the newest ``keep``; their states, oldest first."""
        if keep < 0:
            raise ValueError(f"keep must be >= 0, got {keep}")
        n = len(self._lik) - int(keep)
        if n <= 0:
            return []
        states = [int(s) for s in self._decode()[:n]]
        del self._lik[:n]
        del self._trans[:n]
        self._anchor = states[-1]
        self.committed_count += n
        return states

    def _decode(self) -> np.ndarray:
        if not self._lik:
            return np.zeros(0, dtype=np.int64)
        # Before the first commit, from the prior; then conditioned on the last
        # committed state: one more step from it into the window.
        delta = self.log_init + self._lik[0] if self._anchor is None else self._trans[0][self._anchor] + self._lik[0]
        back = np.zeros((len(self._lik), self.n_states), dtype=np.int64)
        for t in range(1, len(self._lik)):
            delta, back[t] = _step(delta, self._trans[t], self._lik[t])
        return _backtrack(back, int(np.argmax(delta)))


# --------------------------------------------------------------------------- helpers


def _checked(log_init, log_trans, log_lik) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    init = np.asarray(log_init, dtype=np.float64)
    trans = np.asarray(log_trans, dtype=np.float64)
    lik = np.asarray(log_lik, dtype=np.float64)
    if init.ndim != 1 or len(init) == 0:
        raise ValueError(f"log_init must be a non-empty (S,) array, got shape {init.shape}")
    s = len(init)
    if lik.ndim != 2 or lik.shape[1] != s:
        raise ValueError(f"log_lik must be a (T, {s}) array, got shape {lik.shape}")
    n = lik.shape[0]
    if trans.shape != (s, s) and trans.shape != (max(n - 1, 0), s, s):
        raise ValueError(f"log_trans must be ({s}, {s}) or ({max(n - 1, 0)}, {s}, {s}), got shape {trans.shape}")
    for name, arr in (("log_init", init), ("log_trans", trans), ("log_lik", lik)):
        if np.isnan(arr).any():
            raise ValueError(f"{name} must not hold NaN")
    return init, trans, lik


def _trans_at(trans: np.ndarray, step: int) -> np.ndarray:
    return trans if trans.ndim == 2 else trans[step]


def _step(delta: np.ndarray, trans: np.ndarray, lik: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One recursion step: (S,) scores, (S, S) transitions, (S,) likelihoods -> new scores, best predecessors."""
    cand = delta[:, None] + trans  # [previous, next]
    best = np.argmax(cand, axis=0)  # first maximum: the lowest index wins ties
    return np.take_along_axis(cand, best[None, :], axis=0)[0] + lik, best


def _backtrack(back: np.ndarray, last: int) -> np.ndarray:
    path = np.empty(back.shape[0], dtype=np.int64)
    path[-1] = last
    for t in range(back.shape[0] - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path
