"""The synthetic house: scripted people rendered into every camera, with exact ground truth.

Main entry points::

    from synth import SyntheticCamera, get_scenario, list_scenarios, write_scenario
    cam = SyntheticCamera("demo", "cam1", seed=0)      # frame source: cam.frame(i) -> (bgr, true_mask)
    write_scenario("demo", "out/", seed=0)             # videos, site, calibrations, truth
    default_site("out/")                               # site file + calibrations only
"""

from synth.house import HouseOutput, measure_render, write_scenario
from synth.scenario import LightChange, Scenario, ScenarioSpec
from synth.scenarios import (
    DEFAULT_SCENARIO, get_scenario, list_scenarios, scenario_descriptions, scenario_spec,
)
from synth.scene import CAMERA_IDS, default_cameras, default_room, default_site
from synth.source import SyntheticCamera
from synth.truth import Truth, derive_truth, write_truth

__all__ = [
    "CAMERA_IDS", "DEFAULT_SCENARIO", "HouseOutput", "LightChange", "Scenario", "ScenarioSpec", "SyntheticCamera",
    "Truth", "default_cameras", "default_room", "default_site", "derive_truth", "get_scenario",
    "list_scenarios", "measure_render", "scenario_descriptions", "scenario_spec", "write_scenario", "write_truth",
]
