"""The scenario library of the synthetic house.

Every scenario is plain data (:class:`ScenarioSpec`); :func:`get_scenario`
compiles one for a seed. The seed changes the people's build and clothes,
small speed variations, the gait phase, sensor noise and the illumination
drift, never the script. :data:`DEFAULT_SCENARIO` ('demo', 60 s) shows
someone entering, walking, sitting on the sofa, standing up and falling.
"""

from __future__ import annotations

from collections.abc import Callable

from synth.behaviour import (
    Bend, Dwell, Enter, Face, Fall, Kneel, Leave, PersonScript, Sit, Stand, Wait, WaitUntil, Walk,
)
from synth.scenario import LightChange, Scenario, ScenarioSpec
from synth.scene import Room

DEFAULT_SCENARIO = "demo"


def _demo() -> ScenarioSpec:
    return ScenarioSpec(
        "demo", "Someone comes in, sits on the sofa, gets up, walks on and falls forward; lies still.", 60.0,
        (PersonScript(1, (
            Enter(to=("hall", "hall east", "centre", (4.2, 1.2))),
            Sit("sofa middle", 10.0),
            Walk(((4.2, 1.2), "centre", (4.0, 4.1), (3.0, 4.2))),
            Fall("forward"),
        ), start_s=1.0),),
        start_local="17:30:00",
    )


def _walk() -> ScenarioSpec:
    return ScenarioSpec(
        "walk", "One person walks a loop around the room and stops.", 30.0,
        (PersonScript(1, (
            Walk(("hall east", "centre", "south centre", "south east", "east", "north east", "hall east"), 1.1),
            Stand(3.0),
        ), start=(1.2, 4.2, 0.0)),),
    )


def _sit_stand() -> ScenarioSpec:
    return ScenarioSpec(
        "sit_stand", "Sits on a dinner chair, then on the sofa, standing up in between.", 75.0,
        (PersonScript(1, (
            Sit("chair 1", 15.0, via=("west", "table west")),
            Sit("sofa middle", 20.0, via=("table west", "south west", "south centre")),
            Walk(("south centre", "centre")),
        ), start=(1.2, 4.2, 0.0)),),
    )


def _fall(direction: str) -> Callable[[], ScenarioSpec]:
    routes = {
        "forward": ("hall east", "centre"),
        "backward": ("hall east", (6.0, 4.2)),
        "right": ("hall east", "north east", "east", (7.3, 1.0)),
    }

    def spec() -> ScenarioSpec:
        name = "fall_sideways" if direction == "right" else f"fall_{direction}"
        return ScenarioSpec(
            name, f"Walks and falls {direction}; lies still to the end.", 40.0,
            (PersonScript(1, (Walk(routes[direction]), Wait(1.0), Fall(direction)), start=(1.2, 4.2, 0.0)),),
        )

    return spec


def _bend_kneel() -> ScenarioSpec:
    return ScenarioSpec(
        "bend_kneel", "Bends to pick something up, then kneels at the kitchen counter; no fall.", 50.0,
        (PersonScript(1, (
            Walk(("hall east", "centre")),
            Bend(hold_s=2.5),
            Walk(("hall east", "kitchen")),
            Face(facing_deg=90.0),
            Kneel(hold_s=6.0),
            Walk(("hall", "hall east", "north east")),
        ), start=(1.2, 4.2, 0.0)),),
    )


def _long_still() -> ScenarioSpec:
    return ScenarioSpec(
        "long_still", "Walks to the window side and stands still for three minutes, then walks away.", 200.0,
        (PersonScript(1, (
            Walk(("hall east", (5.6, 3.7))),
            Face(facing_deg=0.0),
            Stand(180.0),
            Walk(("hall east", "hall")),
        ), start=(1.2, 4.2, 0.0)),),
    )


def _sit_still_10min() -> ScenarioSpec:
    return ScenarioSpec(
        "sit_still_10min", "Sits still on the sofa for ten minutes, then gets up.", 625.0,
        (PersonScript(1, (
            Sit("sofa left", 600.0, via=("hall east", "centre", (4.2, 1.2))),
            Walk(((4.2, 1.2), "centre")),
        ), start=(1.2, 4.2, 0.0)),),
        start_local="20:00:00",
    )


def _enter_exit() -> ScenarioSpec:
    return ScenarioSpec(
        "enter_exit", "Someone enters through the front door, walks around and leaves.", 50.0,
        (PersonScript(1, (
            Enter(to=("hall", "hall east", "centre")),
            Stand(3.0),
            Leave(via=("hall east", "hall")),
        ), start_s=2.0),),
    )


def _hotspot_dwell() -> ScenarioSpec:
    return ScenarioSpec(
        "hotspot_dwell", "Works in the kitchen, stands by the TV, sits on the sofa, waits at the table.", 150.0,
        (PersonScript(1, (
            Dwell("kitchen", 25.0, via=("hall",)),
            Dwell("TV", 20.0, via=("hall east", "centre", "south centre"), activity="rest"),
            Sit("sofa middle", 25.0),
            Dwell("dinner table", 20.0, via=("south centre", "south west", "table west"), activity="rest"),
            Walk(("table west", "west", "hall")),
        ), start=(1.2, 4.2, 0.0)),),
        start_local="12:00:00",
    )


def _two_pass() -> ScenarioSpec:
    return ScenarioSpec(
        "two_pass", "Two people walk towards each other and pass close (0.55 m between them).", 25.0,
        (
            PersonScript(1, (Walk(((6.9, 4.45),), 1.1), Stand(5.0)), start=(0.9, 4.45, 0.0)),
            PersonScript(2, (Walk(((0.9, 3.9),), 1.1), Stand(5.0)), start=(6.9, 3.9, 180.0)),
        ),
        residents=2,
    )


def _abreast(lanes: tuple[tuple[float, float | None], ...]) -> tuple[PersonScript, ...]:
    """People walking abreast across the living room and back, one per lane ``(y, height_m or None
    for a random height)``: from x = 1.0 to 6.8 m at 1 m/s, 4 s standing, back to x = 1.0 m."""
    return tuple(
        PersonScript(k + 1, (Walk(((6.8, y),), 1.0), Stand(4.0), Walk(((1.0, y),), 1.0)),
                     start=(1.0, y, 0.0), speed_jitter=False, height_m=h)
        for k, (y, h) in enumerate(lanes)
    )


def _side_by_side() -> ScenarioSpec:
    return ScenarioSpec(
        "side_by_side", "Two people walk side by side, 0.6 m apart, stop, and walk back.", 35.0,
        _abreast(((4.5, None), (3.9, None))),
        residents=2,
    )


def _three_abreast() -> ScenarioSpec:
    return ScenarioSpec(
        "three_abreast",
        "Three people walk abreast, shoulder to shoulder (0.5 m between centres), stop, and walk back.", 30.0,
        _abreast(((4.7, None), (4.2, None), (3.7, None))),
        residents=3,
    )


def _child_beside_adult() -> ScenarioSpec:
    return ScenarioSpec(
        "child_beside_adult",
        "A child (1.1 m) walks beside an adult (1.8 m), 0.5 m between centres, stops, and walks back.", 30.0,
        _abreast(((4.5, 1.8), (4.0, 1.1))),
        residents=2,
    )


def _hug() -> ScenarioSpec:
    return ScenarioSpec(
        "hug", "Two people meet in the hall, hug (0.35 m between centres) for five seconds, and part.", 30.0,
        (
            PersonScript(1, (Walk(((3.9, 4.2),), 1.0), Face(toward=(4.25, 4.2)), WaitUntil(8.0), Stand(5.0),
                             Walk(("hall", "kitchen"), 1.0), Stand(5.0)), start=(1.2, 4.2, 0.0), speed_jitter=False),
            PersonScript(2, (Walk(((4.25, 4.2),), 1.0), Face(toward=(3.9, 4.2)), WaitUntil(8.0), Stand(5.0),
                             Walk(("north east", "east"), 1.0), Stand(5.0)), start=(7.0, 4.2, 180.0),
                         speed_jitter=False),
        ),
        residents=2,
    )


def _help_up() -> ScenarioSpec:
    return ScenarioSpec(
        "help_up", "Someone falls sideways in the middle of the room; a second person comes, kneels beside "
        "them while they lie, and both get up and walk apart.", 40.0,
        (
            PersonScript(1, (Walk(("hall east", "centre"), 1.0), Fall("left", lie_s=12.0, get_up=True),
                             Stand(3.0), Walk(("hall east", "hall"), 1.0), Stand(5.0)), start=(1.2, 4.2, 0.0),
                         speed_jitter=False),
            PersonScript(2, (Stand(5.0), Walk(((4.9, 3.65),), 1.0), Face(toward=(4.9, 2.9)),
                             Kneel(hold_s=9.0), Stand(3.0), Walk(("east", "south east"), 1.0), Stand(5.0)),
                         start=(7.0, 4.2, 180.0), speed_jitter=False),
        ),
        residents=2,
    )


def _three_at_table() -> ScenarioSpec:
    return ScenarioSpec(
        "three_at_table", "Three people sit down at the dinner table, stay half a minute, and walk off their "
        "own ways.", 60.0,
        (
            PersonScript(1, (Sit("chair 1", 30.0, via=((0.9, 4.0), "table west")), Walk(("table west", "west")),
                             Stand(5.0)), start=(1.2, 4.2, 0.0)),
            PersonScript(2, (Sit("chair 4", 30.0, via=("table north east",)),
                             Walk(("table north east", "hall east")), Stand(5.0)), start=(4.2, 4.2, 180.0)),
            PersonScript(3, (Sit("chair 2", 30.0, via=("centre", "table east")), Walk(("table east", (3.5, 2.8), (5.0, 3.6), "north east")),
                             Stand(5.0)), start=(7.0, 4.2, 180.0)),
        ),
        residents=3,
    )


def _fall_beside_helper() -> ScenarioSpec:
    return ScenarioSpec(
        "fall_beside_helper", "Two people talk standing 0.7 m apart; one falls sideways away from the other, "
        "who stays standing beside them.", 35.0,
        (
            PersonScript(1, (Walk(((5.5, 3.5),), 1.0), Face(toward=(5.5, 4.2)), WaitUntil(9.0), Stand(4.0),
                             Fall("left")), start=(1.2, 3.5, 0.0), speed_jitter=False),
            PersonScript(2, (Walk(((5.5, 4.2),), 1.0), Face(toward=(5.5, 3.5)), WaitUntil(9.0), Stand(26.0)),
                         start=(1.2, 4.2, 0.0), speed_jitter=False),
        ),
        residents=2,
    )


def _dinner_visit() -> ScenarioSpec:
    return ScenarioSpec(
        "dinner_visit", "The resident cooks; a visitor arrives before seven and they have dinner at the table.",
        300.0,
        (
            PersonScript(1, (
                Stand(50.0, activity="work"),
                Sit("chair 1", 180.0, via=((0.9, 4.0), "table west")),
                Sit("sofa left", None, via=("table west", "south west", "south centre", (4.2, 1.2))),
            ), start=(2.1, 5.0, 90.0)),
            PersonScript(2, (
                Enter(to=("hall",)),
                Walk(((1.6, 4.0),)),
                Face(toward="kitchen"),
                Stand(10.0),
                Sit("chair 3", 200.0, via=("table north west",)),
                Leave(via=("table north west", (0.9, 4.0))),
            ), start_s=20.0, resident=False),
        ),
        start_local="18:56:00",
    )


def _four_people() -> ScenarioSpec:
    return ScenarioSpec(
        "four_people", "Ten minutes with four people: the resident and three visitors; sitting, walking, "
        "a fall and getting up, visitors leaving.", 600.0,
        (
            PersonScript(1, (
                Stand(40.0, activity="work"),
                Sit("sofa left", 120.0, via=("hall", "hall east", "centre", (4.2, 1.2))),
                Dwell("TV", 15.0, activity="rest"),
                Sit("sofa left", 180.0),
                Walk(((4.2, 1.2), "centre", "behind sofa west", (5.0, 2.95))),
                WaitUntil(420.0),
                Fall("left", lie_s=25.0, get_up=True),
                Walk(("hall east", "kitchen")),
                Stand(120.0, activity="work"),
            ), start=(2.1, 5.0, 90.0)),
            PersonScript(2, (
                Enter(to=("hall",)),
                Sit("chair 3", 200.0, via=("table north west",)),
                Dwell("kitchen", 40.0, via=("table north west", (0.9, 4.0), "hall")),
                Sit("chair 3", 150.0, via=("hall", (0.9, 4.0), "table north west")),
                Leave(via=("table north west", (0.9, 4.0))),
            ), start_s=30.0, resident=False),
            PersonScript(3, (
                Enter(to=("hall", (3.5, 4.0))),
                Sit("chair 4", 180.0, via=("table north east",)),
                Walk(("table north east", (5.5, 3.7))),
                Bend(hold_s=2.0),
                Stand(60.0),
                Sit("sofa right", None, via=("north east", "east", (6.8, 1.2))),
            ), start_s=60.0, resident=False, height_m=1.68),
            PersonScript(4, (
                Enter(to=("hall", "hall east", "north east")),
                Stand(40.0),
                Sit("chair 2", 200.0, via=("centre", "table east")),
                Leave(via=("table east", (3.5, 2.8), (3.5, 4.0), "hall")),
            ), start_s=150.0, resident=False),
        ),
        start_local="15:00:00",
    )


def _lights() -> ScenarioSpec:
    return ScenarioSpec(
        "lights", "One person walks while a lamp is switched on (+28 %) and off again.", 60.0,
        (PersonScript(1, (
            Walk(("hall east", "centre", "south centre", "south east", "east", "north east", "hall east", "hall"), 0.9),
            Walk(("hall east", "centre"), 0.9),
            Stand(10.0),
        ), start=(1.2, 4.2, 0.0)),),
        lights=(LightChange(20.0, 1.28), LightChange(45.0, 1.0 / 1.28)),
    )


def _behind_sofa() -> ScenarioSpec:
    return ScenarioSpec(
        "behind_sofa", "Walks behind the sofa (partly hidden), bends and kneels there, walks out.", 45.0,
        (PersonScript(1, (
            Walk(("hall east", "behind sofa west", (5.6, 2.95)), 0.8),
            Face(facing_deg=-90.0),
            Bend(hold_s=3.0),
            Walk(((6.4, 2.95),), 0.6),
            Kneel(hold_s=5.0),
            Walk(("behind sofa east", "east", "south east"), 0.8),
        ), start=(1.2, 4.2, 0.0)),),
    )


SCENARIOS: dict[str, Callable[[], ScenarioSpec]] = {
    "demo": _demo,
    "walk": _walk,
    "sit_stand": _sit_stand,
    "fall_forward": _fall("forward"),
    "fall_backward": _fall("backward"),
    "fall_sideways": _fall("right"),
    "bend_kneel": _bend_kneel,
    "long_still": _long_still,
    "sit_still_10min": _sit_still_10min,
    "enter_exit": _enter_exit,
    "hotspot_dwell": _hotspot_dwell,
    "two_pass": _two_pass,
    "side_by_side": _side_by_side,
    "three_abreast": _three_abreast,
    "child_beside_adult": _child_beside_adult,
    "hug": _hug,
    "help_up": _help_up,
    "three_at_table": _three_at_table,
    "fall_beside_helper": _fall_beside_helper,
    "dinner_visit": _dinner_visit,
    "four_people": _four_people,
    "lights": _lights,
    "behind_sofa": _behind_sofa,
}


def list_scenarios() -> list[str]:
    """Names of the library's scenarios, the default first."""
    return [DEFAULT_SCENARIO] + sorted(n for n in SCENARIOS if n != DEFAULT_SCENARIO)


def scenario_descriptions() -> dict[str, str]:
    """Name -> one-line description, the default first (for a command line's listing)."""
    return {name: f"{SCENARIOS[name]().description} ({SCENARIOS[name]().duration_s:.0f} s)" for name in list_scenarios()}


def scenario_spec(name: str) -> ScenarioSpec:
    """The spec of a named scenario; ValueError listing the names when unknown."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; scenarios are: {', '.join(list_scenarios())}")
    return SCENARIOS[name]()


def get_scenario(name: str | ScenarioSpec | Scenario = DEFAULT_SCENARIO, seed: int = 0, *, room: Room | None = None,
                 utc_offset_hours: float = 0.0) -> Scenario:
    """A compiled scenario by name (or from a spec) for ``seed``."""
    if isinstance(name, Scenario):
        return name
    spec = name if isinstance(name, ScenarioSpec) else scenario_spec(name)
    return Scenario(spec, seed, room=room, utc_offset_hours=utc_offset_hours)
