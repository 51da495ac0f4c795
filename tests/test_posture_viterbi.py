"""Viterbi posture decisions: the aged transition model, flicker against a
frame-wise decision, and the events of the decoded postures (sitting down,
standing up, falls) against their hand-worked times."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_server.events import EventReasoner, FallParams
from fusion_server.posture import (
    DECODED_STATES,
    POSTURES,
    STATE_POSTURE,
    STATES,
    VITERBI_AGES,
    PostureBank,
    PostureEstimator,
    viterbi_aged_log_transitions,
    viterbi_log_transitions,
)
from fusion_server.viterbi import FixedLagViterbi
from test_events import FPS, FRAME_NS, LIE, NS, SIT, STAND, Person, _fall_profiles, _toppling, kinds, run, t_s
from test_posture import VOXEL_M, blend, body_profile


def _bank(decisions: str, **kw) -> PostureBank:
    return PostureBank(voxel_m=VOXEL_M, decisions=decisions, **kw)


# --------------------------------------------------------------------------- transition model


def test_transitions_are_stochastic_and_sticky():
    for dt_s in (0.0, 1 / 15, 1 / 5, 2.0):
        p = np.exp(viterbi_log_transitions(dt_s))
        assert p.shape == (len(DECODED_STATES),) * 2
        np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.exp(viterbi_log_transitions(0.0)), np.eye(len(DECODED_STATES)), atol=1e-12)
    # one frame at 15 fps: staying in the shape `standing` costs about 0.15 nats (it may turn into
    # another standing shape), staying standing in any shape a few hundredths, sitting down about 5.7
    t = viterbi_log_transitions(1 / 15)
    stand, sit = STATES.index("standing"), STATES.index("sitting")
    assert -0.2 < t[stand, stand] < -0.05
    shapes = [i for i, p in enumerate(STATE_POSTURE) if POSTURES[p] == "standing"]
    assert -0.05 < np.log(np.exp(t[stand, shapes]).sum()) < 0
    assert t[stand, sit] == pytest.approx(np.log(0.05 / 15), abs=0.1)


def test_a_young_posture_cannot_change_and_ages_one_step_a_frame_at_15_fps():
    m = VITERBI_AGES
    t = viterbi_aged_log_transitions(1 / 15, 0.4)
    np.testing.assert_allclose(np.exp(t).sum(axis=1), 1.0, atol=1e-9)
    stand, sit, outside = STATES.index("standing"), STATES.index("sitting"), len(STATES)
    raised = STATES.index("standing_raised")
    for a in range(m - 1):
        assert np.isneginf(t[stand * m + a, sit * m + 0])  # too young to sit down
        assert np.isfinite(t[stand * m + a, stand * m + a + 1])  # ages one step
        assert np.isfinite(t[stand * m + a, raised * m + a + 1])  # a shape change keeps the age
        assert np.isneginf(t[stand * m + a, stand * m + a])
    assert np.isfinite(t[stand * m + m - 1, sit * m])  # settled: may sit down, and starts young
    assert np.isneginf(t[stand * m + m - 1, sit * m + m - 1])
    # out of view is always settled, and may end at once
    assert np.isfinite(t[stand * m + m - 1, outside * m + m - 1])
    assert np.isfinite(t[outside * m + m - 1, stand * m])
    # no minimum duration: the plain chain
    np.testing.assert_array_equal(viterbi_aged_log_transitions(1 / 15, 0.0), viterbi_log_transitions(1 / 15))


@pytest.mark.parametrize(("kwargs", "name"), [
    (dict(decisions="hmm"), "decisions"),
    (dict(decisions="viterbi", viterbi_lag_s=1.5), "viterbi_lag_s"),
    (dict(decisions="viterbi", viterbi_lag_s=-0.1), "viterbi_lag_s"),
])
def test_estimator_settings_are_checked(kwargs, name):
    with pytest.raises(ValueError, match=name):
        PostureEstimator(voxel_m=VOXEL_M, **kwargs)


# --------------------------------------------------------------------------- flicker


def _flickering_log_likelihoods() -> np.ndarray:
    """(T, S) log-likelihoods over the decoded states: 4 s standing, then 4 s in
    which every 10th frame starts 3 frames that favour sitting by 4 nats,
    then 4 s standing. Every frame has a body (outside impossible)."""
    frames = 12 * FPS
    lik = np.full((frames, len(DECODED_STATES)), -20.0)
    lik[:, STATES.index("standing")] = 0.0
    lik[:, STATES.index("sitting")] = -4.0
    lik[:, -1] = -np.inf
    for start in range(4 * FPS, 8 * FPS, 10):
        lik[start : start + 3, STATES.index("sitting")] = 0.0
        lik[start : start + 3, STATES.index("standing")] = -4.0
    return lik


def _events_of(postures: list[str]) -> list[str]:
    """Sit and stand events of one still track whose posture, frame by frame, is given by name."""
    from test_events import Est

    reasoner = EventReasoner()
    out = []
    for k, posture in enumerate(postures):
        est = Est(1, 2.0, 2.0, STAND)
        out += reasoner.step(k * FRAME_NS, k, [est], {1: posture})
    return [e.kind for e in out if e.kind in ("sit_down", "stand_up")]


def test_flickering_likelihoods_raise_a_sit_down_frame_by_frame_but_nothing_on_the_viterbi_path():
    lik = _flickering_log_likelihoods()
    frame_wise = [POSTURES[STATE_POSTURE[int(k)]] for k in np.argmax(lik, axis=1)]
    # The first three frames of sitting follow 4 s of standing: a sit_down that
    # never was (and no stand_up, since each sitting spell is too short to be
    # left by standing up).
    assert _events_of(frame_wise) == ["sit_down"]

    m = VITERBI_AGES
    prior = np.full(len(DECODED_STATES) * m, -np.inf)
    prior[m - 1 :: m] = 0.0
    dec = FixedLagViterbi(prior)
    trans = viterbi_aged_log_transitions(1 / FPS, 0.4)
    committed: list[int] = []
    for t, row in enumerate(lik):
        dec.push(np.repeat(row, m), trans if t else None)
        committed += dec.commit(keep=int(0.6 * FPS))
    committed += dec.commit(keep=0)
    decoded = [POSTURES[STATE_POSTURE[s // m]] for s in committed]
    assert set(decoded) == {"standing"}
    assert _events_of(decoded) == []


def test_three_frames_of_sitting_shape_are_no_sit_down_in_either_decision():
    # the estimator itself: a body that takes a seated shape for three frames at a time
    for decisions in ("frame", "viterbi"):
        p = Person(1).hold(4.0, STAND, xy=(1.0, 1.0))
        for _ in range(6):
            p.frames += [(1.0, 1.0, SIT, True)] * 3 + [(1.0, 1.0, STAND, True)] * 7
        p.hold(4.0, STAND)
        assert kinds(run([p], EventReasoner(), bank=_bank(decisions))) == []


# --------------------------------------------------------------------------- decoded postures


def test_readings_lag_by_the_set_delay_and_are_never_taken_back():
    p = Person(2).hold(3.0, STAND, xy=(1.0, 1.0))
    p.move(1.0, lambda f: body_profile(blend("standing", "sitting", f))).hold(4.0, SIT)
    p.move(1.0, lambda f: body_profile(blend("sitting", "standing", f))).hold(3.0, STAND)
    est = PostureEstimator(voxel_m=VOXEL_M, decisions="viterbi", viterbi_lag_s=0.6)
    runs: dict[int, str] = {}
    first = None
    for k, fr in enumerate(p.frames):
        r = est.update(k * FRAME_NS, fr[2])
        if r is None:
            assert k * FRAME_NS < 0.6 * NS + FRAME_NS  # nothing committed yet
            continue
        first = k if first is None else first
        assert r.since_ns <= r.stamp_ns - int(0.6 * NS) + FRAME_NS
        # a run of the committed path, once reported, keeps its posture
        assert runs.setdefault(r.since_ns, r.posture) == r.posture
        assert r.since_ns >= max(runs)
    assert int(round(0.6 * FPS)) <= first <= int(round(0.6 * FPS)) + 1
    assert list(runs.values()) == ["standing", "sitting", "standing"]
    starts = [t_s(s) for s in runs]
    assert 3.0 < starts[1] < 4.0 and 8.0 < starts[2] < 9.0  # inside each movement


def test_sit_down_and_stand_up_on_the_viterbi_path():
    p = Person(2).hold(3.0, STAND, xy=(1.0, 1.0))
    p.move(1.0, lambda f: body_profile(blend("standing", "sitting", f))).hold(6.0, SIT)
    p.move(1.0, lambda f: body_profile(blend("sitting", "standing", f))).hold(3.0, STAND)
    events = run([p], EventReasoner(), bank=_bank("viterbi"))
    assert kinds(events) == ["sit_down", "stand_up"]
    sit, stand = events
    assert 4.0 <= t_s(sit.stamp_ns) <= 4.0 + 1.5  # movement ends at 4 s
    assert 11.0 - 0.5 <= t_s(stand.stamp_ns) <= 11.0 + 1.5  # and at 11 s
    assert sit.details["from_posture"] == "standing" and stand.details["from_posture"] == "sitting"


@pytest.mark.parametrize("lag_s", [0.0, 0.6, 1.0])
def test_a_fall_on_the_viterbi_path_is_raised_within_1_5_s_of_landing(lag_s):
    fall_start_s, fall_s = 3.0, 0.8
    p = Person(1).hold(fall_start_s, STAND, xy=(3.0, 3.0))
    p.move(fall_s, _fall_profiles(), (3.8, 3.0), _toppling).hold(40.0, LIE)
    events = run([p], EventReasoner(falls=FallParams(long_lie_s=30.0)), bank=_bank("viterbi", viterbi_lag_s=lag_s))
    assert kinds(events) == ["fall", "long_lie"]
    fall, lie = events
    landed = fall_start_s + fall_s
    assert 0 < t_s(fall.stamp_ns) - landed <= 1.5
    assert fall_start_s < t_s(fall.details["fall_stamp_ns"]) < landed
    assert fall.details["from_posture"] == "standing"
    assert t_s(lie.stamp_ns) - t_s(fall.details["fall_stamp_ns"]) == pytest.approx(30.0, abs=2 / FPS)


def test_getting_up_after_a_fall_on_the_viterbi_path():
    # up onto the knees in 2 s, then up from them in 2 s (a body does not go from lying to kneeling
    # in one frame: a top rising a metre at once is a track jumping to someone else, no stand_up)
    p = Person(8).hold(2.0, STAND, xy=(3.0, 3.0)).move(0.8, _fall_profiles(), (3.0, 3.7), _toppling).hold(5.0, LIE)
    p.move(2.0, lambda f: body_profile("kneeling", tilt_deg=90 * (1 - f)))
    p.move(2.0, lambda f: body_profile(blend("kneeling", "standing", f))).hold(4.0, STAND)
    assert kinds(run([p], EventReasoner(), bank=_bank("viterbi"))) == ["fall", "stand_up"]


def test_frames_without_a_body_are_outside_and_keep_the_last_reading():
    est = PostureEstimator(voxel_m=VOXEL_M, decisions="viterbi", viterbi_lag_s=0.2)
    k = 0
    for _ in range(2 * FPS):
        r = est.update(k * FRAME_NS, SIT)
        k += 1
    assert r.posture == "sitting"
    empty = np.zeros_like(SIT)
    for _ in range(FPS):
        assert est.update(k * FRAME_NS, empty) is r
        k += 1
    for _ in range(2 * FPS):
        r2 = est.update(k * FRAME_NS, STAND)
        k += 1
    assert r2.posture == "standing"
    # the standing spell began with the body's return, not before
    assert r2.since_ns == (3 * FPS) * FRAME_NS
