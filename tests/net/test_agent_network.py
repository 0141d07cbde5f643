"""The agent's choice of path and its reading of OpenVPN's state, without a tunnel."""

from __future__ import annotations

import pytest

from bridgeos_agent.network import DIRECT, CloudNetwork
from bridgeos_agent.robotconfig import parse_robot_config
from bridgeos_agent.tls import InsecureMaster, http_base
from bridgeos_agent.vpn import parse_state


@pytest.mark.parametrize(
    ("line", "parsed"),
    [
        (">STATE:1700000000,CONNECTED,SUCCESS,10.8.0.2,192.0.2.1,1194,,", ("CONNECTED", "10.8.0.2")),
        ("1700000000,RECONNECTING,connection-reset,,,,,", ("RECONNECTING", None)),
        (">STATE:1700000000,WAIT,,,,,,", ("WAIT", None)),
        (">INFO:OpenVPN Management Interface Version 5", None),
        ("END", None),
    ],
)
def test_management_state_lines_are_read(line, parsed):
    assert parse_state(line) == parsed


def network(tmp_path, master: str = "wss://cloud.example:8443", **kw) -> CloudNetwork:
    return CloudNetwork(master=master, robot="r1", token="brt_x", data_dir=tmp_path, say=lambda line: None, **kw)


def test_without_a_tunnel_the_agent_goes_direct_and_verifies_tls(tmp_path):
    net = network(tmp_path)
    target = net.target()
    assert (target.path, target.url) == (DIRECT, "wss://cloud.example:8443/ws/robot/")
    assert target.connect_options()["ssl"].check_hostname
    assert net.path_point("vpn")["value"] == 1.0 and net.path_point(DIRECT)["labels"] == {"path": "direct"}


async def test_a_vpn_config_is_not_a_path_until_the_tunnel_is_up(tmp_path):
    net = network(tmp_path, firewall_mode="off")
    config = parse_robot_config(
        {
            "subnets": {"local": "10.64.0.0/24", "cloud": "10.80.0.0/24"},
            "vpn": {"enabled": False, "master": "wss://10.8.0.1:8443"},
        }
    )
    net.apply_config(config)
    assert net.preferred() == DIRECT
    await net.close()


def test_plain_ws_away_from_this_machine_needs_permission(tmp_path):
    with pytest.raises(InsecureMaster):
        network(tmp_path, master="ws://cloud.example:8000")
    assert network(tmp_path, master="ws://cloud.example:8000", allow_insecure=True).target().connect_options() == {}
    assert http_base("wss://cloud.example:8443/") == "https://cloud.example:8443"
    assert http_base("ws://127.0.0.1:8000") == "http://127.0.0.1:8000"


def test_the_robot_config_refuses_a_vpn_master_that_is_not_a_websocket_url():
    with pytest.raises(ValueError, match=r"vpn\.master"):
        parse_robot_config({"vpn": {"enabled": True, "master": "http://10.8.0.1"}})
    with pytest.raises(ValueError, match="tls_ca"):
        parse_robot_config({"tls_ca": "not a certificate"})
