"""Zenoh configs: every process's settings come from common.transport, as they were written by hand before."""

from __future__ import annotations

import json

import pytest
import zenoh

from common.site import ZenohSettings
from common.transport import TransportError, private_config, zenoh_config


def _by_hand(values: dict) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in values.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


@pytest.mark.parametrize("multicast", [False, True])
def test_router_config_is_the_routers_settings(multicast: bool) -> None:
    conf = zenoh_config(ZenohSettings(multicast_scouting=multicast), mode="router", listen=["tcp/0.0.0.0:7447"])
    assert str(conf) == str(_by_hand({"mode": "router", "listen/endpoints": ["tcp/0.0.0.0:7447"],
                                      "scouting/multicast/enabled": multicast,
                                      "transport/shared_memory/enabled": False}))


def test_default_settings_keep_scouting_and_shared_memory_off() -> None:
    conf = zenoh_config(mode="router", listen=["tcp/127.0.0.1:7000"])
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]


def test_a_client_waits_for_its_router() -> None:
    conf = zenoh_config(mode="client", connect=["tcp/127.0.0.1:7000"])
    assert json.loads(conf.get_json("connect/timeout_ms")) == -1


def test_private_config_turns_off_scouting_and_shared_memory_only() -> None:
    assert str(private_config()) == str(_by_hand({"scouting/multicast/enabled": False,
                                                  "transport/shared_memory/enabled": False}))
    assert json.loads(private_config().get_json("connect/endpoints")) == []


@pytest.mark.parametrize("kwargs, name", [({"mode": "bogus"}, "mode"), ({"listen": ["nowhere"]}, "listen/endpoints")])
def test_a_refused_value_names_the_setting(kwargs: dict, name: str) -> None:
    with pytest.raises(TransportError, match=f"zenoh setting {name} = "):
        zenoh_config(**kwargs)
    assert issubclass(TransportError, ValueError)
