"""Scripted behaviours and the scenario library: timing, plausibility, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from synth.behaviour import (
    FALL_S, SIT_DOWN_S, STAND_UP_S, Fall, Leave, PersonScript, Return, Sit, Stand, Walk, compile_person,
)
from synth.scenario import ScenarioSpec
from synth.scenarios import DEFAULT_SCENARIO, get_scenario, list_scenarios, scenario_spec
from synth.scene import default_room

REQUIRED = {"walk", "sit_stand", "fall_forward", "fall_backward", "fall_sideways", "bend_kneel", "long_still",
            "sit_still_10min", "enter_exit", "hotspot_dwell", "two_pass", "side_by_side", "dinner_visit",
            "four_people", "lights", "behind_sofa"}


CLOSE_CONTACT_M = {"hug": 0.35}
"""Scenarios whose people come closer than 0.5 m on purpose, and how close."""


@pytest.fixture(scope="module")
def library():
    return {name: get_scenario(name, 0) for name in list_scenarios()}


def test_library_lists_every_scenario_default_first():
    names = list_scenarios()
    assert names[0] == DEFAULT_SCENARIO
    assert REQUIRED <= set(names) and len(names) >= 12
    with pytest.raises(ValueError, match="scenarios are: demo, "):
        get_scenario("no_such_thing")


def test_default_scenario_shows_entering_walking_sitting_and_a_fall(library):
    sc = library[DEFAULT_SCENARIO]
    assert 50 <= sc.spec.duration_s <= 70
    kinds = {kind for p in sc.people for _, kind, _ in p.events}
    assert {"sit_down", "stand_up", "fall"} <= kinds
    st = sc.states[0]
    assert not st["present"][0] and st["present"][-1] and st["moving"].any()


def test_sizes_range_from_one_person_one_minute_to_four_people_ten_minutes(library):
    assert min(s.spec.duration_s for s in library.values()) <= 60
    big = library["four_people"]
    assert len(big.people) == 4 and big.spec.duration_s >= 600


def test_scripts_fit_their_scenarios_and_people_keep_apart(library):
    room = default_room()
    floor_boxes = [b for b in room.boxes if b.min_m[2] < 1.0]
    for name, sc in library.items():
        assert sc.end_time_s() <= sc.spec.duration_s + 1e-6, name
        states = sc.states
        for i, a in enumerate(states):
            # Walking people never walk through furniture.
            xy = a["xy"][a["moving"] & a["present"]]
            for b in floor_boxes:
                inside = ((xy[:, 0] > b.min_m[0] + 0.02) & (xy[:, 0] < b.max_m[0] - 0.02)
                          & (xy[:, 1] > b.min_m[1] + 0.02) & (xy[:, 1] < b.max_m[1] - 0.02))
                assert not inside.any(), (name, b.name)
            # Present people are in the room or in the corridor behind the door.
            p = a["xy"][a["present"]]
            assert np.all(p[:, 0] >= -2.4) and np.all(p[:, 0] <= 8) and np.all(p[:, 1] >= 0) and np.all(p[:, 1] <= 6)
            for b_ in states[i + 1:]:
                both = a["present"] & b_["present"]
                if both.any():
                    gap = np.linalg.norm(a["xy"][both] - b_["xy"][both], axis=1).min()
                    assert gap >= CLOSE_CONTACT_M.get(name, 0.5), (name, gap)


def test_walking_speeds_are_human(library):
    for name, sc in library.items():
        for st in sc.states:
            step = np.linalg.norm(np.diff(st["xy"], axis=0), axis=1) * sc.fps
            moving = st["moving"][1:] & st["present"][1:] & st["present"][:-1]
            if moving.any():
                assert step[moving].max() <= 1.5, name
                assert np.percentile(step[moving], 90) >= 0.55, name


def test_transitions_take_realistic_time():
    room = default_room()
    script = PersonScript(1, (Sit("sofa middle", 5.0, via=((4.2, 1.2),)), Walk(((4.05, 3.0),)), Fall("backward")),
                          start=(4.2, 3.0, -90.0))
    tl = compile_person(script, room, np.random.default_rng(0), 60.0)
    keyed = [s for s in tl.segments if s.switches]
    events = [(s.switches[-1].event, s.t1 - s.t0) for s in keyed]
    assert events == [("sit_down", pytest.approx(SIT_DOWN_S)), ("stand_up", pytest.approx(STAND_UP_S)),
                      ("fall", pytest.approx(FALL_S))]
    assert 0.8 <= FALL_S <= 1.0 and 1.5 <= STAND_UP_S <= 2.0
    # The fall is a fast drop: most of the height is lost in the last third.
    fall = keyed[-1]
    t = np.linspace(fall.t0, fall.t1, 31)
    z = fall.evaluate(t)[:, 2]
    assert z[10] > z[0] - 0.15 * (z[0] - z[-1])
    assert z[-1] < 0.2


def test_seated_hips_are_at_seat_height():
    room = default_room()
    for seat in ("chair 2", "sofa left"):
        tl = compile_person(PersonScript(1, (Stand(0.5),), start=f"seat:{seat}"), room, np.random.default_rng(1), 2.0)
        q, label, _, _ = tl.evaluate(np.array([1.0]))
        s = room.seat(seat)
        assert label[0] == 1
        assert q[0, 2] == pytest.approx(s.height_m + tl.shape.seat_offset_m)
        assert abs(q[0, 2] - s.height_m) < 0.12
        np.testing.assert_allclose(q[0, :2], s.xy_m)


def test_side_by_side_walkers_stay_abreast():
    a, b = get_scenario("side_by_side", 3).states
    both = a["present"] & b["present"]
    np.testing.assert_allclose(a["xy"][both, 0], b["xy"][both, 0], atol=1e-9)
    np.testing.assert_allclose(np.abs(a["xy"][both, 1] - b["xy"][both, 1]), 0.6, atol=1e-9)


def test_same_seed_same_people_other_seed_other_people():
    a = get_scenario("two_pass", 5)
    b = get_scenario("two_pass", 5)
    c = get_scenario("two_pass", 6)
    for pa, pb in zip(a.states, b.states):
        np.testing.assert_array_equal(pa["q"], pb["q"])
    assert [p.shape for p in a.people] == [p.shape for p in b.people]
    assert [p.shape for p in a.people] != [p.shape for p in c.people]


def test_bad_scripts_are_rejected_with_the_reason():
    room = default_room()
    with pytest.raises(ValueError, match="first step must be Enter"):
        compile_person(PersonScript(1, (Stand(1.0),)), room, np.random.default_rng(0), 5.0)
    with pytest.raises(ValueError, match="speed_mps"):
        compile_person(PersonScript(1, (Walk(((2.0, 2.0),), 5.0),), start=(1.0, 1.0, 0.0)), room,
                       np.random.default_rng(0), 5.0)
    with pytest.raises(ValueError, match="direction"):
        compile_person(PersonScript(1, (Fall("up"),), start=(1.0, 1.0, 0.0)), room, np.random.default_rng(0), 5.0)
    with pytest.raises(ValueError, match="unique"):
        ScenarioSpec("x", "", 1.0, (PersonScript(1, (), start=(1, 1, 0)), PersonScript(1, (), start=(2, 2, 0))))
    with pytest.raises(ValueError, match="scenarios are"):
        scenario_spec("nope")


def test_a_person_who_leaves_can_come_back_by_a_door_or_over_an_open_edge():
    room = default_room()
    rng = lambda: np.random.default_rng(3)  # noqa: E731
    by_door = PersonScript(1, (Leave("front door", via=((2.0, 4.3),)), Return(6.0, "front door", to=((3.0, 3.0),)),
                               Stand(2.0)), start=(3.0, 4.3, 180.0))
    tl = compile_person(by_door, room, rng(), 40.0)
    (a0, b0), (a1, b1) = tl.present
    # gone for exactly the time away; back in the corridor beyond the door, then at the waypoint
    assert a0 == 0.0 and a1 - b0 == pytest.approx(6.0)
    q, _, _, present = tl.evaluate(np.array([b0 + 3.0, a1, b1 - 1.0]))
    assert present.tolist() == [False, True, True]
    assert np.allclose(q[1, :2], room.door("front door").outside_xy_m)
    assert np.allclose(q[2, :2], (3.0, 3.0), atol=1e-6)
    assert b1 == 40.0
    # over an open edge: vanish at the last waypoint, appear at the first waypoint of the way back
    edge = PersonScript(1, (Leave(None, via=((7.5, 1.0),)), Return(4.0, None, to=((7.5, 5.0), (6.0, 5.0)))),
                        start=(5.0, 1.0, 0.0))
    tl = compile_person(edge, room, rng(), 30.0)
    (_, b0), (a1, _) = tl.present
    q, _, _, _ = tl.evaluate(np.array([b0 - 1e-6, a1, 29.0]))
    assert np.allclose(q[:, :2], [(7.5, 1.0), (7.5, 5.0), (6.0, 5.0)], atol=1e-3)
    # the same draws as without the way back: the body is the same
    alone = compile_person(PersonScript(1, (Leave(None, via=((7.5, 1.0),)),), start=(5.0, 1.0, 0.0)), room, rng(), 30.0)
    assert alone.shape == tl.shape and len(alone.present) == 1
    with pytest.raises(ValueError, match="Return must follow a Leave"):
        compile_person(PersonScript(1, (Return(3.0, None, to=((1.0, 1.0),)),), start=(2.0, 2.0, 0.0)), room, rng(), 9.0)
    with pytest.raises(ValueError, match="where to vanish"):
        compile_person(PersonScript(1, (Leave(None),), start=(2.0, 2.0, 0.0)), room, rng(), 9.0)


def test_clothes_replace_only_the_shirt_trousers_and_sleeves():
    room = default_room()
    plain = PersonScript(1, (Stand(1.0),), start=(2.0, 2.0, 0.0))
    dressed = PersonScript(1, (Stand(1.0),), start=(2.0, 2.0, 0.0), clothes=((1, 2, 3), (4, 5, 6), False))
    a = compile_person(plain, room, np.random.default_rng(8), 2.0).shape
    b = compile_person(dressed, room, np.random.default_rng(8), 2.0).shape
    assert (b.shirt_bgr, b.trousers_bgr, b.long_sleeves) == ((1, 2, 3), (4, 5, 6), False)
    assert (a.height_m, a.width, a.skin_bgr, a.hair_bgr, a.shoes_bgr) == (b.height_m, b.width, b.skin_bgr, b.hair_bgr,
                                                                          b.shoes_bgr)


def test_time_stamps_and_time_of_day():
    sc = get_scenario("dinner_visit")
    assert sc.stamp_ns(0) == sc.start_ns
    assert sc.stamp_ns(15) - sc.start_ns == 1_000_000_000
    assert sc.stamp_ns(7) - sc.start_ns == round(7 * 1e9 / 15)
    assert 18.9 < sc.local_hour(0) < 19.0
    assert sc.start_ns % 86_400_000_000_000 == (18 * 3600 + 56 * 60) * 1_000_000_000
    shifted = get_scenario("dinner_visit", utc_offset_hours=2.0)
    assert sc.start_ns - shifted.start_ns == 2 * 3600 * 10**9


def test_lighting_drifts_slowly_and_lamps_switch_suddenly():
    sc = get_scenario("lights")
    g = np.array([sc.gain(i) for i in range(sc.n_frames)])
    assert np.abs(np.diff(g[:290])).max() < 0.002
    assert g[:290].max() - g[:290].min() > 0.005
    assert g[305] / g[295] == pytest.approx(1.28, rel=0.02)
    assert g[45 * 15 + 10] / g[45 * 15 - 5] == pytest.approx(1 / 1.28, rel=0.02)
